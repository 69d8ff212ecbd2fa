"""Render a Gaussian model into any pinhole camera of its frame.

model = load_model("runs/splat")            # a training folder, a checkpoint or a .ply
out = render(model, camera, pose)           # numpy: color (H, W, 3), depth (H, W), alpha (H, W)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from services.colmap_model import Camera, Pose
from services.geometry import look_at

from .backend import rasterization, resolve_backend
from .model import activated, sh_degree_of, splats_from_tensors
from .ply import load_ply
from .projection import FAR, NEAR, viewmat_from_pose


def latest_checkpoint(folder: str | Path) -> Path | None:
    ckpts = sorted(Path(folder).glob("ckpts/step_*.pt"))
    return ckpts[-1] if ckpts else None


def load_model(path: str | Path) -> torch.nn.ParameterDict:
    """Gaussians from a .ply file, a checkpoint (.pt) or a training folder (its point_cloud.ply, else
    its latest checkpoint)."""
    path = Path(path)
    if path.is_dir():
        if (path / "point_cloud.ply").exists():
            return load_ply(path / "point_cloud.ply")
        ckpt = latest_checkpoint(path)
        if ckpt is None:
            raise FileNotFoundError(f"{path} holds neither point_cloud.ply nor ckpts/step_*.pt")
        path = ckpt
    if path.suffix == ".ply":
        return load_ply(path)
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    return splats_from_tensors(ckpt["splats"], requires_grad=False)


def render(
    model: dict[str, torch.Tensor],
    camera: Camera,
    pose: Pose,
    backend: str = "auto",
    sh_degree: int | None = None,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    near_plane: float = NEAR,
    far_plane: float = FAR,
) -> dict[str, np.ndarray]:
    """Render `model` (model.py layout) into `camera` (its pinhole part: K; distortion is ignored) at
    `pose` (cam_from_world); only the Gaussians whose centres' z-depth lies in (near_plane, far_plane).

    Returns numpy float32 arrays: color (H, W, 3) in [0, 1] (over `background`), depth (H, W) the expected
    z-depth along the optical axis normalised by alpha (sum w_i z_i / sum w_i; 0 where nothing was hit;
    multiply by alpha for the raw accumulated depth) and alpha (H, W) the accumulated opacity.
    """
    backend = resolve_backend(backend)
    dev = torch.device("cuda" if backend == "cuda" else "cpu")
    with torch.no_grad():
        p = activated({k: v.detach().to(dev) for k, v in model.items()})
        deg = sh_degree_of(model) if sh_degree is None else sh_degree
        out, alpha, _ = rasterization(
            p["means"],
            p["quats"],
            p["scales"],
            p["opacities"],
            p["sh"],
            viewmat_from_pose(pose.R, pose.t).to(dev),
            torch.as_tensor(camera.K, dtype=torch.float32, device=dev),
            int(camera.width),
            int(camera.height),
            sh_degree=deg,
            backgrounds=torch.tensor([*background, 0.0], device=dev),
            render_mode="RGB+ED",
            backend=backend,
            near_plane=near_plane,
            far_plane=far_plane,
        )
    out, alpha = out.cpu().numpy(), alpha[..., 0].cpu().numpy()
    depth = np.where(alpha > 0, out[..., 3], 0.0).astype(np.float32)
    return {"color": np.clip(out[..., :3], 0, 1).astype(np.float32), "depth": depth, "alpha": alpha}


def lowered_pose(pose: Pose, factor: float = 0.5, ground_z: float = 0.0) -> Pose:
    """The camera moved down to `factor` of its height above the plane z = ground_z and turned towards the
    point where its optical axis met that plane (its ground target)."""
    c = pose.center
    axis = pose.R[2]  # optical axis in the world frame
    if axis[2] >= -1e-6:
        raise ValueError("the optical axis does not meet the ground plane")
    target = c + axis * (ground_z - c[2]) / axis[2]
    new_c = np.array([c[0], c[1], ground_z + factor * (c[2] - ground_z)])
    return look_at(new_c, target)
