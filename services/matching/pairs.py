"""Candidate aerial-ground image pairs: every combination, or those the POS says can overlap.

Pairs are written hloc style, one `name0 name1` per line, aerial first.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose, read_cameras_json
from services.pos import LocalFrame, PosRecord, read_pos_csv
from shared.logging import stage

logger = logging.getLogger("midview.pairs")

Pair = tuple[str, str]

confs: dict[str, dict[str, Any]] = {
    "all": {"method": "all"},
    "pos": {
        "method": "pos",
        # distances along the ground camera's optical axis; one of these points (or the camera itself) must
        # project into the aerial image. Street views see far: 15 m alone lost 9 of 26 matchable pairs of
        # the `small` preset, [15, 30, 60] keeps all of them (162 of 600 pairs instead of 87).
        "look_ahead_m": [15.0, 30.0, 60.0],
        "camera_height_m": 1.5,  # ground cameras above the terrain: look-ahead points stay above it
        "margin": 0.1,  # accept projections up to this fraction of the image size outside it (POS noise)
        "min_heading_cos": -0.2,  # horizontal viewing directions must not be opposed
        "skip_nadir": True,  # nadir aerial images share almost nothing with ground views
        "nadir_pitch_deg": -80.0,
        "max_distance_m": None,  # optional: horizontal aerial-to-target distance limit
    },
}


# -- pair files --------------------------------------------------------------------------------
def write_pairs(path: str | Path, pairs: list[Pair]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    return path


def read_pairs(path: str | Path) -> list[Pair]:
    """Pairs of a text file (`name0 name1` per line; blank and `#` lines ignored)."""
    pairs = []
    for i, line in enumerate(Path(path).read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"{path} line {i}: expected two image names, got {line!r}")
        pairs.append((parts[0], parts[1]))
    return pairs


def split_sets(names: list[str]) -> tuple[list[str], list[str]]:
    """(aerial names, ground names), each sorted."""
    aerial = sorted(n for n in names if n.split("/", 1)[0] == "aerial")
    ground = sorted(n for n in names if n.split("/", 1)[0] == "ground")
    return aerial, ground


def all_pairs(aerial: list[str], ground: list[str]) -> list[Pair]:
    return [(a, g) for a in aerial for g in ground]


# -- POS pruning -------------------------------------------------------------------------------
def local_poses(records: list[PosRecord]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray | None]]:
    """Camera centres in an ENU frame around the mean position, and R_world_from_cam (None if absent).
    The POS attitude is relative to the local ENU at each image; over a site it equals the frame's."""
    lat = np.array([r.lat for r in records])
    lon = np.array([r.lon for r in records])
    h = np.array([r.h for r in records])
    frame = LocalFrame(float(lat.mean()), float(lon.mean()), float(h.mean()))
    xyz = frame.from_wgs84(lat, lon, h)
    centers = {r.name: xyz[i] for i, r in enumerate(records)}
    rotations = {r.name: r.R_world_from_cam for r in records}
    return centers, rotations


def _heading(R: np.ndarray) -> np.ndarray | None:
    """Unit horizontal direction of the optical axis, None when (nearly) vertical."""
    f = R[:2, 2]
    n = float(np.linalg.norm(f))
    return f / n if n > 1e-3 else None


def _pitch_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arcsin(np.clip(R[2, 2], -1.0, 1.0))))


def ground_targets(center: np.ndarray, R: np.ndarray, conf: dict[str, Any], z_terrain: float) -> np.ndarray:
    """Points (K, 3) a ground camera looks at: along its optical axis (kept above the terrain), and itself."""
    dists = np.atleast_1d(np.asarray(conf["look_ahead_m"], float))
    pts = center[None] + dists[:, None] * R[:, 2][None]
    pts[:, 2] = np.maximum(pts[:, 2], z_terrain)
    return np.concatenate([pts, center[None]], 0)


def sees_any(camera: Camera, pose: Pose, points: np.ndarray, margin: float) -> bool:
    """Whether any point lies in front of the camera and projects inside its image (+ margin)."""
    uv, z = pose.project(camera.K, points)
    mx, my = margin * camera.width, margin * camera.height
    inside = (
        (z > 0)
        & (uv[:, 0] >= -mx)
        & (uv[:, 0] <= camera.width + mx)
        & (uv[:, 1] >= -my)
        & (uv[:, 1] <= camera.height + my)
    )
    return bool(inside.any())


def pairs_from_pos(
    aerial: list[str],
    ground: list[str],
    records: list[PosRecord],
    cameras: dict[str, Camera],
    conf: dict[str, Any] | None = None,
) -> list[Pair]:
    """(aerial, ground) pairs that can overlap according to the POS. Images without a POS record
    or without attitude keep all their pairs."""
    conf = {**confs["pos"], **(conf or {})}
    recs = {r.name: r for r in records if r.name in set(aerial) | set(ground)}
    if not recs:
        logger.warning("no POS record names these images: keeping every pair")
        return all_pairs(aerial, ground)
    centers, rots = local_poses(list(recs.values()))
    gz = [centers[g][2] for g in ground if g in centers]
    z_terrain = float(np.median(gz)) - conf["camera_height_m"] if gz else -np.inf

    pairs: list[Pair] = []
    n_nadir = 0
    for a in aerial:
        Ra = rots.get(a)
        if Ra is None:
            pairs += [(a, g) for g in ground]
            continue
        if conf["skip_nadir"] and _pitch_deg(Ra) < conf["nadir_pitch_deg"]:
            n_nadir += 1
            continue
        cam_a = cameras.get(a.split("/", 1)[0])
        if cam_a is None:
            raise ValueError(f"cameras.json has no camera for the set of {a}")
        pose_a = Pose.from_center(Ra, centers[a])
        head_a = _heading(Ra)
        for g in ground:
            Rg = rots.get(g)
            if Rg is None:
                pairs.append((a, g))
                continue
            head_g = _heading(Rg)
            if head_a is not None and head_g is not None and head_a @ head_g <= conf["min_heading_cos"]:
                continue
            targets = ground_targets(centers[g], Rg, conf, z_terrain)
            if conf.get("max_distance_m") is not None:
                d = np.linalg.norm(targets[:, :2] - centers[a][None, :2], axis=1)
                targets = targets[d <= conf["max_distance_m"]]
            if len(targets) and sees_any(cam_a, pose_a, targets, conf["margin"]):
                pairs.append((a, g))
    logger.info(
        "POS pairs: %d of %d kept (%d nadir aerial images skipped)",
        len(pairs),
        len(aerial) * len(ground),
        n_nadir,
    )
    return pairs


# -- entry points ------------------------------------------------------------------------------
def get_pairs(
    conf: dict[str, Any],
    names: list[str],
    pos_path: str | Path | None = None,
    cameras_path: str | Path | None = None,
) -> list[Pair]:
    """Candidate (aerial, ground) pairs among image names, by conf["method"] ("all" or "pos")."""
    aerial, ground = split_sets(names)
    if conf["method"] == "all":
        return all_pairs(aerial, ground)
    if conf["method"] == "pos":
        if pos_path is None or cameras_path is None:
            raise ValueError("POS pairs need a POS file and cameras.json")
        return pairs_from_pos(aerial, ground, read_pos_csv(pos_path), read_cameras_json(cameras_path), conf)
    raise ValueError(f"unknown pairs method {conf['method']!r}")


def main(
    conf: dict[str, Any],
    names: list[str],
    output: str | Path,
    pos_path: str | Path | None = None,
    cameras_path: str | Path | None = None,
) -> Path:
    """Write the candidate pairs of `names` to `output` (one `aerial ground` per line)."""
    with stage(f"pairs:{conf['method']}", logger):
        pairs = get_pairs(conf, names, pos_path, cameras_path)
        logger.info("%d pairs -> %s", len(pairs), output)
        return write_pairs(output, pairs)
