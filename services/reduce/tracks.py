"""Aerial track completion: the aerial points of the reducer observed in every aerial image that sees them.

A render keypoint matched to one or two aerial images becomes a 3D point of the aerial model (the
reducer triangulates it). Every other aerial image whose pose is known and that sees the point can
observe it too: its projection there is known to a pixel or two, so the observation is found by
*guided matching*: the image's keypoints within `px` of the projection, the one whose descriptor is
most like the point's (the mean of its current observations' descriptors), accepted when that
similarity reaches `min_similarity` and clearly beats the runner-up within the radius (`margin`).
A keypoint observes at most one point (the most similar one wins), and a point is only sought in
images whose viewing direction is within `max_angle_deg` of one of its observations (so facades are
not looked for from behind).

Every aerial-ground link through a point then reaches all the aerial images of its track, not only
the few a view was matched against: the transfer of section 3.2.3 extended by aerial-aerial
correspondences that the aerial model's geometry and the descriptors both confirm.

    obs = complete_tracks(conf, X, obs, cameras, poses, features)
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose

logger = logging.getLogger("midview.tracks")

default_conf: dict[str, Any] = {
    "enabled": True,
    "px": 3.0,  # search radius around the projection (full-resolution aerial pixels)
    "min_similarity": 0.8,  # cosine similarity of the descriptors (unit-norm ALIKED/SIFT descriptors)
    "margin": 0.05,  # the best keypoint must beat the second best within the radius by this much
    "max_angle_deg": 40.0,  # between the new viewing ray and the nearest ray of the point's observations
    "border_px": 4.0,  # projections this close to the image border are not searched
}

# an observation: (aerial image name, keypoint index, score)
Observation = tuple[str, int, float]


def _unit(d: np.ndarray) -> np.ndarray:
    d = np.asarray(d, np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def point_descriptors(
    obs: list[list[Observation]], descriptors: dict[str, np.ndarray], dim: int
) -> np.ndarray:
    """(P, D) unit mean descriptor of each point's observations (zeros for a point without any)."""
    out = np.zeros((len(obs), dim), np.float32)
    for p, items in enumerate(obs):
        ds = [descriptors[a][i] for a, i, _ in items if a in descriptors]
        if ds:
            out[p] = np.mean(_unit(np.stack(ds)), 0)
    return _unit(out) * (np.linalg.norm(out, axis=1, keepdims=True) > 0)


def viewing_angles_ok(
    X: np.ndarray, centers_obs: list[np.ndarray], center: np.ndarray, max_deg: float
) -> np.ndarray:
    """(P,) whether the ray from `center` to each point is within max_deg of one of its observations'
    rays (centers_obs[p]: (k, 3) centres of the cameras observing point p)."""
    cos_max = np.cos(np.radians(max_deg))
    ok = np.zeros(len(X), bool)
    for p, cs in enumerate(centers_obs):
        if len(cs) == 0:
            continue
        u = X[p] - center
        u = u / max(np.linalg.norm(u), 1e-12)
        v = X[p][None] - cs
        v = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        ok[p] = bool((v @ u).max() >= cos_max)
    return ok


def guided_matches(
    uv: np.ndarray,
    point_desc: np.ndarray,
    keypoints: np.ndarray,
    descriptors: np.ndarray,
    px: float,
    min_similarity: float,
    margin: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Guided matching of projected points (uv (P, 2), point_desc (P, D)) to an image's keypoints
    (K, 2) with descriptors (K, D). Returns (point index, keypoint index, similarity) of the accepted
    matches, one-to-one (a keypoint claimed by several points goes to the most similar)."""
    from scipy.spatial import cKDTree

    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
    if len(uv) == 0 or len(keypoints) == 0:
        return empty
    tree = cKDTree(np.asarray(keypoints, np.float64))
    desc = _unit(descriptors)
    rows_p, rows_k, rows_s = [], [], []
    for p, nb in enumerate(tree.query_ball_point(np.asarray(uv, np.float64), r=px)):
        if not nb:
            continue
        nb = np.asarray(nb, np.int64)
        sim = desc[nb] @ point_desc[p]
        order = np.argsort(-sim, kind="stable")
        best = float(sim[order[0]])
        second = float(sim[order[1]]) if len(order) > 1 else -1.0
        if best >= min_similarity and best - second >= margin:
            rows_p.append(p)
            rows_k.append(int(nb[order[0]]))
            rows_s.append(best)
    if not rows_p:
        return empty
    p, k, s = np.array(rows_p), np.array(rows_k), np.array(rows_s, np.float32)
    order = np.lexsort((p, -s.astype(np.float64)))  # most similar first, then by point
    _, first = np.unique(k[order], return_index=True)
    keep = np.sort(order[first])
    return p[keep], k[keep], s[keep]


def complete_tracks(
    conf: dict | None,
    X: np.ndarray,
    obs: list[list[Observation]],
    cameras: dict[str, Camera],
    poses: dict[str, Pose],
    keypoints: dict[str, np.ndarray],
    descriptors: dict[str, np.ndarray],
) -> tuple[list[list[Observation]], dict]:
    """The points' observations extended to every aerial image of `poses` with keypoints and
    descriptors (see the module docstring). Existing observations are kept; a keypoint already observing
    a point is not given to another. Returns (observations, stats). Deterministic: images in name
    order, points in index order."""
    conf = {**default_conf, **(conf or {})}
    X = np.asarray(X, float).reshape(-1, 3)
    out = [sorted(items) for items in obs]
    stats = {"points": len(X), "added": 0, "images": 0}
    if not conf["enabled"] or len(X) == 0 or not descriptors:
        return out, stats
    dim = next(iter(descriptors.values())).shape[1]
    pdesc = point_descriptors(out, descriptors, dim)
    has_desc = np.linalg.norm(pdesc, axis=1) > 0
    used: dict[str, set[int]] = {}
    for items in out:
        for a, i, _ in items:
            used.setdefault(a, set()).add(i)
    centers_obs = [
        np.array([poses[a].center for a, _, _ in items if a in poses]).reshape(-1, 3) for items in out
    ]
    added = [[] for _ in out]
    for a in sorted(poses):
        if a not in keypoints or a not in descriptors or a not in cameras:
            continue
        cam, pose = cameras[a], poses[a]
        uv, z = pose.project(cam.K, X)
        b = conf["border_px"]
        inside = (
            (z > 0)
            & (uv[:, 0] >= b)
            & (uv[:, 0] < cam.width - b)
            & (uv[:, 1] >= b)
            & (uv[:, 1] < cam.height - b)
        )
        seen = np.array([any(o[0] == a for o in items) for items in out], bool)
        cand = np.flatnonzero(inside & ~seen & has_desc)
        if len(cand) == 0:
            continue
        cand = cand[
            viewing_angles_ok(X[cand], [centers_obs[p] for p in cand], pose.center, conf["max_angle_deg"])
        ]
        if len(cand) == 0:
            continue
        free = np.ones(len(keypoints[a]), bool)
        free[list(used.get(a, ()))] = False
        kidx = np.flatnonzero(free)
        pi, ki, sim = guided_matches(
            uv[cand],
            pdesc[cand],
            keypoints[a][kidx],
            descriptors[a][kidx],
            conf["px"],
            conf["min_similarity"],
            conf["margin"],
        )
        stats["images"] += int(len(pi) > 0)
        for p, k, s in zip(cand[pi], kidx[ki], sim, strict=True):
            best = max((sc for _, _, sc in out[p]), default=1.0)
            added[p].append((a, int(k), float(min(s, best))))
            used.setdefault(a, set()).add(int(k))
    for p, extra in enumerate(added):
        if extra:
            out[p] = sorted(out[p] + extra)
            stats["added"] += len(extra)
    logger.info(
        "track completion: %d observations added to %d points in %d images",
        stats["added"],
        len(X),
        stats["images"],
    )
    return out, stats
