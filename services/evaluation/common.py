"""Ground truth of a synthetic scene folder (docs/formats.md), read directly from its files."""

from __future__ import annotations

import csv
from pathlib import Path

import h5py
import numpy as np

from services.colmap_model import Camera, Pose, read_model


class EvaluationError(ValueError):
    """Bad input to an evaluation: missing scene folder or ground truth, unreadable match file or model."""


def image_set(name: str) -> str:
    """The set of an image name: its first path component ('aerial', 'ground')."""
    return name.split("/", 1)[0]


def require_scene(scene_dir: Path, *files: str) -> Path:
    """Check that the scene folder and the given files under it exist."""
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise EvaluationError(f"scene folder {scene_dir} does not exist")
    for f in files:
        if not (scene_dir / f).exists():
            raise EvaluationError(f"{scene_dir}: ground truth {f} is missing (not a synthetic scene folder?)")
    return scene_dir


def read_gt_model(scene_dir: Path) -> tuple[dict[str, Camera], dict[str, Pose]]:
    """True cameras and poses (gt/sparse) of a scene folder."""
    path = require_scene(scene_dir, "gt/sparse") / "gt" / "sparse"
    try:
        return read_model(path)
    except Exception as e:  # pycolmap raises plain RuntimeErrors / ValueErrors
        raise EvaluationError(f"{path}: cannot read the true model ({e})") from e


def read_covisible(path: Path, min_overlap: float = 0.0) -> list[tuple[str, str, float]]:
    """Co-visible pairs (aerial, ground, overlap) of gt/covisible.csv with overlap >= min_overlap."""
    rows = []
    with open(path, newline="") as f:
        reader = csv.DictReader(line for line in f if line.strip() and not line.startswith("#"))
        missing = {"aerial", "ground", "overlap"} - set(reader.fieldnames or [])
        if missing:
            raise EvaluationError(f"{path}: columns {sorted(missing)} missing")
        for r in reader:
            ov = float(r["overlap"])
            if ov >= min_overlap:
                rows.append((r["aerial"], r["ground"], ov))
    return rows


class DepthMaps:
    """Lazy, cached access to gt/depth.h5 (one float32 HxW z-depth per image, 0 = no surface)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise EvaluationError(f"depth maps {self.path} are missing")
        self.h5 = h5py.File(self.path, "r")
        self._cache: dict[str, np.ndarray] = {}

    def __enter__(self) -> DepthMaps:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._cache.clear()
        if self.h5.id.valid:
            self.h5.close()

    def __contains__(self, name: str) -> bool:
        return name.replace("/", "|") in self.h5

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._cache:
            key = name.replace("/", "|")
            if key not in self.h5:
                raise EvaluationError(f"{self.path}: no depth map for {name}")
            self._cache[name] = np.asarray(self.h5[key][()], np.float32)
        return self._cache[name]


def lookup_depth(depth: np.ndarray, uv: np.ndarray, interp: str = "bilinear") -> np.ndarray:
    """Depth (N,) at COLMAP pixels uv (N, 2); 0 outside the image or where there is no surface.

    Depth at row i, col j belongs to pixel (j + 0.5, i + 0.5). 'nearest' takes that pixel.
    'bilinear' interpolates the 2x2 pixel centres around uv where they are all valid and continuous
    (max/min <= 1.05), and falls back to nearest across depth edges, so that a sub-pixel keypoint on
    a slanted surface gets a sub-pixel accurate depth without blending foreground and background.
    """
    h, w = depth.shape
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    out = np.zeros(len(uv), np.float64)
    inside = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not inside.any():
        return out
    x, y = uv[inside, 0], uv[inside, 1]
    d = depth[np.minimum(y.astype(int), h - 1), np.minimum(x.astype(int), w - 1)].astype(np.float64)
    if interp == "bilinear":
        u, v = np.clip(x - 0.5, 0, w - 1), np.clip(y - 0.5, 0, h - 1)
        j0, i0 = (
            np.minimum(u.astype(int), w - 2 if w > 1 else 0),
            np.minimum(v.astype(int), h - 2 if h > 1 else 0),
        )
        j1, i1 = np.minimum(j0 + 1, w - 1), np.minimum(i0 + 1, h - 1)
        fu, fv = u - j0, v - i0
        q = np.stack([depth[i0, j0], depth[i0, j1], depth[i1, j0], depth[i1, j1]], 1).astype(np.float64)
        wts = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], 1)
        ok = (q.min(1) > 0) & (q.max(1) <= 1.05 * q.min(1))
        d = np.where(ok, (q * wts).sum(1), d)
    elif interp != "nearest":
        raise ValueError(f"unknown depth interpolation {interp!r}")
    out[inside] = d
    return out
