"""Ground images whose matches fit two poses alike (services.sfm.combined).

Along a street a facade's windows repeat: a ground pair matched one window along the street passes the
essential matrix, and where half of a pair's matches are such a shift the mapper can register the image
between the two places (the demo's G0020 registered 1.11 m and 3.19 m off through a pair of 86 matches, 43
of them right). Its matches then hold two poses: the best pose's inliers, and among the rest a second pose
nearly as well supported, somewhere else. Such an image is ambiguous: the product reports it unregistered
rather than place it at one of two places.

    hyp = competing_poses(kp, X, camera, max_error_px=8.0)
    hyp.ambiguous(conf)  # the second pose's support within min_ratio of the first's, min_separation_m away
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import pycolmap

logger = logging.getLogger("midview.combined_sfm")

default_conf: dict[str, Any] = {
    "enabled": True,
    # the second pose (the best among the first's outliers) makes the image ambiguous when it holds at
    # least min_ratio of the first pose's inliers (and min_inliers) and stands min_separation_m from it
    "min_ratio": 0.5,
    "min_inliers": 15,
    "min_separation_m": 0.5,
    "max_error_px": 8.0,  # the inlier threshold (the mapper's abs_pose_max_error)
    "seed": 0,
    # an image at least this share of whose points one other ground image observes hangs on that image
    # (hanging_images): its pose is that one pair's, unchecked. None: not judged
    "hanging_min_share": 0.95,
}


@dataclass
class CompetingPoses:
    """The best pose of an image's 2D-3D correspondences and the best among its outliers."""

    first_inliers: int
    second_inliers: int
    separation_m: float  # between the two poses' centres (inf when there is no second pose)

    def ambiguous(self, conf: dict[str, Any]) -> bool:
        return self.second_inliers >= max(
            int(conf["min_inliers"]), conf["min_ratio"] * self.first_inliers
        ) and self.separation_m >= float(conf["min_separation_m"])

    def reason(self) -> str:
        return (
            f"two poses fit its matches alike ({self.first_inliers} and {self.second_inliers} inliers,"
            f" {self.separation_m:.2f} m apart)"
        )


def _best_pose(kp: np.ndarray, X: np.ndarray, camera: pycolmap.Camera, max_error_px: float, seed: int):
    """(centre (3,), inlier mask) of pycolmap's LO-RANSAC absolute pose, or None."""
    if len(kp) < 4:
        return None
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = float(max_error_px)
    opts.ransac.random_seed = int(seed)
    try:
        out = pycolmap.estimate_and_refine_absolute_pose(
            np.ascontiguousarray(kp, np.float64), np.ascontiguousarray(X, np.float64), camera, opts
        )
    except Exception:  # noqa: BLE001 - pycolmap raises on degenerate input: no pose
        return None
    if out is None:
        return None
    m = np.asarray(out["cam_from_world"].matrix())
    return -m[:, :3].T @ m[:, 3], np.asarray(out["inlier_mask"], bool)


def competing_poses(
    kp: np.ndarray, X: np.ndarray, camera: pycolmap.Camera, max_error_px: float = 8.0, seed: int = 0
) -> CompetingPoses:
    """The best pose of the correspondences kp (N, 2) pixels - X (N, 3) world points and the best pose
    of the first's outliers."""
    first = _best_pose(kp, X, camera, max_error_px, seed)
    if first is None:
        return CompetingPoses(0, 0, float("inf"))
    c1, inl = first
    rest = ~inl
    second = _best_pose(kp[rest], X[rest], camera, max_error_px, seed)
    if second is None:
        return CompetingPoses(int(inl.sum()), 0, float("inf"))
    c2, inl2 = second
    return CompetingPoses(int(inl.sum()), int(inl2.sum()), float(np.linalg.norm(c2 - c1)))


def image_correspondences(
    rec: pycolmap.Reconstruction, image_id: int, matches: dict[int, np.ndarray], keypoints: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """An image's 2D-3D correspondences through its verified matches (`matches`: {other image id: (M, 2)
    this image's keypoint, the other's}) with the registered images' points that at least two images other
    than it observe (points it alone would triangulate move with it); (kp (N, 2), X (N, 3))."""
    seen: set[tuple[int, int]] = set()
    kp, X = [], []
    for other, m in matches.items():
        if other not in rec.images or not rec.images[other].has_pose:
            continue
        pts = rec.images[other].points2D
        for k_self, k_other in np.asarray(m).reshape(-1, 2):
            p = pts[int(k_other)]
            if not p.has_point3D() or (int(k_self), p.point3D_id) in seen:
                continue
            point = rec.points3D[p.point3D_id]
            if sum(el.image_id != image_id for el in point.track.elements) < 2:
                continue
            seen.add((int(k_self), p.point3D_id))
            kp.append(keypoints[int(k_self)])
            X.append(point.xyz)
    return np.asarray(kp, float).reshape(-1, 2), np.asarray(X, float).reshape(-1, 3)


def verified_matches(db: pycolmap.Database, image_ids: set[int]) -> dict[int, dict[int, np.ndarray]]:
    """The database's verified matches of `image_ids`: {image id: {other id: (M, 2) its keypoint, the
    other's}}."""
    out: dict[int, dict[int, np.ndarray]] = {i: {} for i in image_ids}
    pair_ids, geometries = db.read_two_view_geometries()
    for pid, tvg in zip(pair_ids, geometries, strict=True):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        m = np.asarray(tvg.inlier_matches).reshape(-1, 2)
        if not len(m):
            continue
        if a in out:
            out[a][b] = m
        if b in out:
            out[b][a] = m[:, ::-1]
    return out


def ambiguous_images(
    rec: pycolmap.Reconstruction, candidates: list[int], db_path: str, conf: dict[str, Any]
) -> dict[int, CompetingPoses]:
    """The registered images of `candidates` whose verified matches fit two poses alike (conf:
    default_conf)."""
    if not conf.get("enabled", True) or not candidates:
        return {}
    db = pycolmap.Database.open(str(db_path))
    try:
        keypoints = {i: db.read_keypoints(i)[:, :2].astype(np.float64) for i in candidates}
        matches = verified_matches(db, set(candidates))
    finally:
        db.close()
    out, seen = {}, []
    for i in candidates:
        kp, X = image_correspondences(rec, i, matches[i], keypoints[i])
        hyp = competing_poses(kp, X, rec.images[i].camera, conf["max_error_px"], conf["seed"])
        seen.append(f"{rec.images[i].name} {hyp.first_inliers}/{hyp.second_inliers} {hyp.separation_m:.2f} m")
        if hyp.ambiguous(conf):
            out[i] = hyp
    logger.info("two poses (best inliers / second's, apart): %s", "; ".join(seen))
    return out


def hanging_images(
    rec: pycolmap.Reconstruction,
    image_ids: list[int],
    min_share: float,
    partners: dict[str, set[str]] | None = None,
) -> dict[int, str]:
    """The images of `image_ids` nearly all of whose 3D points (at least `min_share`) one other ground
    image also observes, and (with `partners`: each image's verified ground pairs) with no verified pair to
    another registered ground image: their pose rests on that one pair's matches, which nothing else
    checks (on the demo's `isprs` G0020 registered 3.28 m off, every one of its 62 points G0017's, its
    one pair a repeated facade). On a walk an image's points are mostly its next neighbour's too, but its
    pairs with the neighbours beyond check them. {image_id: reason}."""
    names = {im.image_id: im.name for im in rec.images.values() if im.has_pose}
    posed = set(names.values())
    out = {}
    for image_id in image_ids:
        im = rec.images[image_id]
        if partners is not None:
            if len(partners.get(im.name, set()) & posed) > 1:
                continue
        points = {p.point3D_id for p in im.points2D if p.has_point3D()}
        shared: dict[int, int] = {}
        for pid in points:
            for other in {e.image_id for e in rec.points3D[pid].track.elements} - {image_id}:
                if names.get(other, "").startswith("ground/"):
                    shared[other] = shared.get(other, 0) + 1
        if not points or not shared:
            continue
        top, n = max(shared.items(), key=lambda kv: (kv[1], -kv[0]))
        if n >= min_share * len(points):
            out[image_id] = (
                f"hangs on {names[top]}: {n} of its {len(points)} points are that image's too, a pair"
                " nothing else checks"
            )
    return out
