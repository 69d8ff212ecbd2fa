"""Step 1 of the reducer: each rendered view's inlier matches as observations of the aerial and ground
images (image keypoint, render keypoint, score, view, 3D point through the rendered depth), and the
inputs they come from (views.json, the per-view match files, the matching features' cache)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.colmap_model import Camera, Pose
from shared.matchfile import PairMatches

logger = logging.getLogger("midview.reduce")


@dataclass
class ViewData:
    """What the reducer needs of one rendered view."""

    name: str
    camera: Camera
    pose: Pose
    depth: np.ndarray | None  # (H, W) z-depth, 0 = none; None: no 3D checks for this view
    keypoints: dict[str, np.ndarray]  # image name -> keypoints (render: views/NAME.png)
    pairs: list[PairMatches]  # (render, image) pairs with inliers


def image_set(name: str) -> str:
    return name.split("/", 1)[0]


# -- step 1: transfer within one view ---------------------------------------------------------------
def render_points(view: ViewData, idx: np.ndarray, conf: dict) -> np.ndarray:
    """3D points (n, 3) of render keypoints `idx` through the view's depth; NaN where the depth is
    missing or on a depth edge. All NaN when the view has no depth."""
    from services.geometry import lookup_depth

    rname = next(n for n in view.keypoints if image_set(n) == "views")
    out = np.full((len(idx), 3), np.nan)
    if view.depth is None or len(idx) == 0:
        return out
    kp = view.keypoints[rname][idx].astype(np.float64)
    d = lookup_depth(view.depth, kp, conf["depth_interp"])
    ok = d > 0
    w = int(conf.get("edge_window") or 0)
    if w > 1 and ok.any():
        from scipy.ndimage import maximum_filter, minimum_filter

        dep = view.depth.astype(np.float32)
        valid = dep > 0
        lo = minimum_filter(np.where(valid, dep, np.inf), size=w)
        hi = maximum_filter(np.where(valid, dep, 0.0), size=w)
        hh, ww = dep.shape
        r = np.clip(kp[:, 1].astype(int), 0, hh - 1)
        c = np.clip(kp[:, 0].astype(int), 0, ww - 1)
        ratio = hi[r, c] / np.maximum(lo[r, c], 1e-6)
        holes = minimum_filter(valid.astype(np.uint8), size=w)[r, c] == 0
        ok &= (ratio <= conf["edge_ratio"]) & ~holes
    if ok.any():
        out[ok] = view.pose.unproject(view.camera.K, kp[ok], d[ok])
    return out


def view_observations(view: ViewData, view_index: int, conf: dict) -> dict[str, dict[str, np.ndarray]]:
    """The view's inlier matches as observations per image: arrays i (the image's keypoint), ir (the
    render keypoint), score, view and X (the render keypoint's 3D point, NaN without depth)."""
    rname = next(n for n in view.keypoints if image_set(n) == "views")
    per: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for pm in view.pairs:
        if pm.name1 == rname:
            pm = pm.swapped()
        if pm.name0 != rname or image_set(pm.name1) not in ("aerial", "ground"):
            continue
        keep = np.ones(len(pm.matches), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
        keep &= np.asarray(pm.scores) >= conf["min_score"]
        m = pm.matches[keep].astype(np.int64)
        order = np.argsort(m[:, 0], kind="stable")
        per[pm.name1] = (m[order, 0], m[order, 1], np.asarray(pm.scores, np.float32)[keep][order])
    idx = np.unique(np.concatenate([r for r, _, _ in per.values()])) if per else np.zeros(0, np.int64)
    X_all = render_points(view, idx, conf)
    out = {}
    for name, (ir, i, sc) in sorted(per.items()):
        out[name] = {
            "i": i,
            "ir": ir,
            "score": sc,
            "view": np.full(len(i), view_index, np.int64),
            "X": X_all[np.searchsorted(idx, ir)] if len(ir) else np.zeros((0, 3)),
        }
    return out


def _cat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def take(d: dict[str, np.ndarray], sel) -> dict[str, np.ndarray]:
    return {k: v[sel] for k, v in d.items()}


def link_identity(oa: dict, og: dict) -> tuple[np.ndarray, np.ndarray]:
    """The paper's transfer: observations of the same render keypoint in the same view (indices into
    oa and og)."""
    big = np.int64(1) << 32
    ka, kg = oa["view"] * big + oa["ir"], og["view"] * big + og["ir"]
    _, ia, ig = np.intersect1d(ka, kg, assume_unique=True, return_indices=True)
    return ia, ig


def load_views(
    views_json: str | Path, match_files: list[str | Path], with_depth: bool = True
) -> tuple[list[ViewData], dict]:
    """The rendered views (views/views.json, with depths) and their match files, sorted by view name."""
    from services.matching import read_view_matches
    from services.views import read_render

    views_json = Path(views_json)
    doc = json.loads(views_json.read_text())
    entries = {v["name"]: v for v in doc["views"]}
    out = []
    for path in match_files:
        name, kps, pairs, _ = read_view_matches(path)
        v = entries.get(name)
        if v is None:
            logger.warning("%s: view %s is not in %s; skipped", path, name, views_json)
            continue
        depth = None
        if with_depth:
            try:
                depth = read_render(views_json.parent, v)[1]
            except FileNotFoundError:
                logger.warning("view %s has no depth: no 3D checks for its matches", name)
        out.append(
            ViewData(
                name,
                Camera(**v["camera"]),
                Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float)),
                depth,
                kps,
                pairs,
            )
        )
    return sorted(out, key=lambda v: v.name), doc


def load_aerial_features(path: str | Path, names: list[str]) -> dict[str, dict[str, np.ndarray]]:
    """Keypoints and descriptors of the aerial images `names` found in a feature cache."""
    import h5py

    from services.matching import load_features

    path = Path(path)
    if not path.is_file():
        logger.warning("no feature cache %s: aerial tracks are not completed", path)
        return {}
    with h5py.File(path, "r") as h5:
        present = [n for n in names if n in h5]
    return {n: load_features(path, n) for n in present}


def collect_keypoints(
    views: list[ViewData], aerial_features: dict[str, dict[str, np.ndarray]] | None
) -> dict[str, np.ndarray]:
    """The keypoints of every aerial and ground image, from the views' match files and the feature cache;
    ValueError when two sources disagree (match files from other feature caches)."""
    keypoints: dict[str, np.ndarray] = {}
    for v in views:
        for n, kp in v.keypoints.items():
            if image_set(n) == "views":
                continue
            if n not in keypoints:
                keypoints[n] = kp
            elif keypoints[n].shape != kp.shape:
                raise ValueError(f"{v.name}: keypoints of {n} differ from another view's (feature caches?)")
    for n, f in sorted((aerial_features or {}).items()):
        if n in keypoints and keypoints[n].shape != f["keypoints"].shape:
            raise ValueError(f"keypoints of {n} differ between the match files and the feature cache")
        keypoints.setdefault(n, np.asarray(f["keypoints"]))
    return keypoints


def observations(views: list[ViewData], conf: dict) -> dict[str, dict[str, np.ndarray]]:
    """Every image's observations through every view (view_observations of each, concatenated)."""
    parts: dict[str, list[dict]] = {}
    for i, v in enumerate(views):
        for name, o in view_observations(v, i, conf).items():
            parts.setdefault(name, []).append(o)
    return {n: _cat(p) for n, p in sorted(parts.items())}
