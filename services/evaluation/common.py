"""Ground truth of a synthetic scene folder (docs/formats.md), read directly from its files."""

from __future__ import annotations

import csv
from pathlib import Path

import h5py
import numpy as np

from services.colmap_model import Camera, Pose, read_model
from services.geometry import lookup_depth  # noqa: F401  (re-exported: the evaluation's depth look-up)


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
