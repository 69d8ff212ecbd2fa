"""Ground truth of a synthetic scene folder (docs/formats.md): reading it back, and the co-visibility
computation used when writing it. Light imports only (no numba).

    gt = load_gt(scene_dir)
    gt.poses["aerial/A0001.jpg"]          # Pose (cam_from_world), true
    gt.cameras["ground/G0001.jpg"].K      # intrinsics of that image
    gt.depth("ground/G0001.jpg")          # (H, W) float32 z-depth, 0 = sky
    gt.covisible                          # [(aerial, ground, overlap)], overlap >= 0.05
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from services.colmap_model import Camera, Pose, read_model
from services.pos import LocalFrame

DEPTH_FILE = "gt/depth.h5"
COVIS_FILE = "gt/covisible.csv"


def depth_key(name: str) -> str:
    """HDF5 dataset name of an image name ('/' -> '|')."""
    return name.replace("/", "|")


def read_depth(scene_dir: str | Path, name: str) -> np.ndarray:
    """True z-depth (H, W) float32 of image `name` ("aerial/A0001.jpg"); 0 where nothing was hit.

    Depth at (row i, col j) belongs to the COLMAP pixel (j + 0.5, i + 0.5) (the pixel's centre ray).
    """
    path = Path(scene_dir) / DEPTH_FILE
    with h5py.File(path, "r") as f:
        key = depth_key(name)
        if key not in f:
            raise KeyError(f"{path}: no depth map for {name}")
        return np.asarray(f[key][()], np.float32)


def read_covisible(scene_dir: str | Path, min_overlap: float = 0.0) -> list[tuple[str, str, float]]:
    """Co-visible (aerial, ground, overlap) pairs of gt/covisible.csv with overlap >= min_overlap."""
    rows = []
    with open(Path(scene_dir) / COVIS_FILE, newline="") as f:
        for r in csv.DictReader(f):
            if float(r["overlap"]) >= min_overlap:
                rows.append((r["aerial"], r["ground"], float(r["overlap"])))
    return rows


@dataclass
class SceneGT:
    """Everything true about a synthetic scene, keyed by image name ("aerial/A0001.jpg")."""

    root: Path
    cameras: dict[str, Camera]  # per image name
    poses: dict[str, Pose]  # per image name, cam_from_world in the local ENU frame
    covisible: list[tuple[str, str, float]]  # (aerial, ground, overlap), sorted
    meta: dict = field(default_factory=dict)  # gt/scene.json
    frame: LocalFrame | None = None  # WGS84 origin of the local ENU frame

    def names(self, image_set: str | None = None) -> list[str]:
        """Image names, sorted; only those of `image_set` ("aerial", "ground") when given."""
        return sorted(n for n in self.poses if image_set is None or n.split("/", 1)[0] == image_set)

    def depth(self, name: str) -> np.ndarray:
        """(H, W) float32 z-depth of image `name` (see read_depth)."""
        return read_depth(self.root, name)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The true surface points (N, 3) and their colours (N, 3) uint8 stored in gt/sparse."""
        import pycolmap

        rec = pycolmap.Reconstruction(str(self.root / "gt" / "sparse"))
        pts = sorted(rec.points3D.items())
        xyz = np.array([p.xyz for _, p in pts], float).reshape(-1, 3)
        rgb = np.array([p.color for _, p in pts], np.uint8).reshape(-1, 3)
        return xyz, rgb


def load_gt(scene_dir: str | Path) -> SceneGT:
    """Read gt/sparse, gt/covisible.csv and gt/scene.json of a scene folder written by services.synth."""
    root = Path(scene_dir)
    cams, poses = read_model(root / "gt" / "sparse")
    meta = json.loads((root / "gt" / "scene.json").read_text())
    o = meta.get("origin")
    frame = LocalFrame(o["lat0"], o["lon0"], o["h0"]) if o else None
    return SceneGT(root, cams, poses, read_covisible(root), meta, frame)


# --------------------------------------------------------------------------- computing it


def pixel_grid(depth: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP pixels (N, 2) on a grid every `step` px with a valid depth, and those depths (N,)."""
    h, w = depth.shape
    ii, jj = np.mgrid[step // 2 : h : step, step // 2 : w : step]
    d = depth[ii, jj].astype(np.float64)
    ok = d > 0
    uv = np.stack([jj[ok] + 0.5, ii[ok] + 0.5], 1).astype(np.float64)
    return uv, d[ok]


def visible_fraction(
    X: np.ndarray, cam: Camera, pose: Pose, depth: np.ndarray, rel: float = 0.01, abs_tol: float = 0.2
) -> float:
    """Fraction of world points X (N, 3) that project into the image (cam, pose) in front of it, with a
    true depth there (nearest pixel) agreeing within rel * z + abs_tol (not occluded)."""
    if len(X) == 0:
        return 0.0
    uv, z = pose.project(cam.K, X)
    h, w = depth.shape
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not ok.any():
        return 0.0
    d = depth[uv[ok, 1].astype(int), uv[ok, 0].astype(int)].astype(np.float64)
    good = (d > 0) & (np.abs(d - z[ok]) <= rel * z[ok] + abs_tol)
    return float(good.sum()) / len(X)


def write_covisible(path: Path, rows: list[tuple[str, str, float]]) -> Path:
    """Write (aerial, ground, overlap) rows, sorted by name, overlap with 4 decimals."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["aerial", "ground", "overlap"])
        for a, g, ov in sorted(rows):
            w.writerow([a, g, f"{ov:.4f}"])
    return path


# what a rendered survey folder holds (services.synth.main writes it); benches and the demo reuse a folder
# that has all of it
SCENE_FILES = (
    "images",
    "pos.csv",
    "cameras.json",
    "gt/sparse",
    "gt/depth.h5",
    "gt/covisible.csv",
    "gt/scene.json",
)


def scene_complete(scene: Path) -> bool:
    """Whether a synthetic survey folder holds everything services.synth.main writes."""
    return all((Path(scene) / f).exists() for f in SCENE_FILES)
