"""Standard 3DGS PLY files (binary little endian), as written by the 3DGS code and opened by common viewers.

Vertex properties: x, y, z, nx, ny, nz (zeros), f_dc_0..2, f_rest_0..(3 (K - 1) - 1) (channel-major:
f_rest_{c * (K - 1) + k}), opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .model import splats_from_tensors


def _fields(n_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def save_ply(splats: dict[str, torch.Tensor], path: str | Path) -> Path:
    """Write Gaussians (the model.py layout) to a 3DGS PLY file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t = {k: v.detach().cpu().float() for k, v in splats.items()}
    n = len(t["means"])
    rest = t["shN"].transpose(1, 2).reshape(n, 3 * t["shN"].shape[1])  # (N, K-1, 3) -> channel-major
    cols = [t["means"], torch.zeros(n, 3), t["sh0"].reshape(n, 3), rest, t["opacities"][:, None], t["scales"]]
    data = torch.cat([*cols, t["quats"]], 1).numpy().astype("<f4")
    names = _fields(rest.shape[1])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {f}" for f in names] + ["end_header"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(np.ascontiguousarray(data).tobytes())
    tmp.replace(path)
    return path


def load_ply(path: str | Path, requires_grad: bool = False) -> torch.nn.ParameterDict:
    """Read a 3DGS PLY file (binary little endian, float properties) into the model.py layout."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little endian PLY files are supported")
    n, props, in_vertex = 0, [], False
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n, in_vertex = int(parts[2]), True
        elif parts[:1] == ["element"]:
            in_vertex = False
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] not in ("float", "float32"):
                raise ValueError(f"{path}: property {parts[-1]} is {parts[1]}, expected float")
            props.append(parts[-1])
    data = np.frombuffer(raw, dtype="<f4", count=n * len(props), offset=end).reshape(n, len(props))
    col = {p: i for i, p in enumerate(props)}

    def get(names: list[str]) -> torch.Tensor:
        return torch.from_numpy(data[:, [col[f] for f in names]].astype(np.float32))

    n_rest = sum(p.startswith("f_rest_") for p in props)
    if n_rest % 3:
        raise ValueError(f"{path}: {n_rest} f_rest properties is not a multiple of 3")
    tensors = {
        "means": get(["x", "y", "z"]),
        "sh0": get(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :],
        "shN": get([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, n_rest // 3).transpose(1, 2),
        "opacities": get(["opacity"])[:, 0],
        "scales": get(["scale_0", "scale_1", "scale_2"]),
        "quats": get(["rot_0", "rot_1", "rot_2", "rot_3"]),
    }
    return splats_from_tensors({k: v.contiguous() for k, v in tensors.items()}, requires_grad=requires_grad)
