"""A POS check of geometrically verified image pairs.

Geometric verification alone keeps wrong pairs when the matches are consistently wrong: repeated
structure (window grids, road markings) or a learned matcher between images rotated against each other
give 20 to 50 matches that one essential matrix or homography explains, and such pairs link the wrong
parts of the scene. With POS attitudes for both images, the relative rotation R (cam2 from cam1) is
known to a few degrees, and the verified inlier rays x1, x2 must fit it:

- long baselines (the POS baseline over `baseline_sigmas` times its uncertainty): some translation t
  with x2 . (t x R x1) = 0 (2-point RANSAC, angular threshold `epipolar_deg`) must explain at least
  `min_consistent` of the inliers, and the POS baseline itself must fit them: their median angular
  epipolar error below `epipolar_deg` plus the baseline's direction uncertainty, atan(sigma / b);
- short baselines (images of one station, or POS noise larger than the baseline): the angle between
  R x1 and x2 is the parallax, below `max_rotation_deg` plus atan((baseline + its uncertainty) / (depth
  / 2)); the depth (distance to the scene) is triangulated from the long-baseline pairs that passed
  (the median), and without any the short pairs are not checked.

Pairs that fail are removed from the database (their two-view geometry) before mapping.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from services.pos import DEFAULT_STD_XY, DEFAULT_STD_Z, LocalFrame, PosRecord

logger = logging.getLogger("midview.sfm.verify")

default_conf: dict[str, Any] = {
    "check": True,
    "max_rotation_deg": 10.0,  # POS attitude uncertainty of a relative rotation
    "epipolar_deg": 4.0,
    "min_consistent": 0.8,
    "baseline_sigmas": 3.0,
    "default_std_xy": DEFAULT_STD_XY,  # metres, when the POS gives none
    "default_std_z": DEFAULT_STD_Z,
    "seed": 0,
}


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(_unit(a) * _unit(b), -1), -1.0, 1.0)))


def pose_from_pos(r: PosRecord, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_world_from_cam, centre) in the frame's ENU, None without attitude."""
    if r.R_world_from_cam is None:
        return None
    R = frame.rotation_to_enu_at(r.lat, r.lon).T @ r.R_world_from_cam
    return R, frame.from_wgs84(r.lat, r.lon, r.h)[0]


def position_sigma(r: PosRecord, conf: dict) -> float:
    """3D standard deviation (m) of a POS position."""
    sxy, sz = r.std_xy or conf["default_std_xy"], r.std_z or conf["default_std_z"]
    return float(np.sqrt(2 * sxy**2 + sz**2))


def fit_translation(
    x1: np.ndarray, x2: np.ndarray, R: np.ndarray, threshold_deg: float, seed: int = 0, iters: int = 200
) -> tuple[np.ndarray | None, np.ndarray]:
    """Direction t (cam2 frame) with x2 . (t x R x1) = 0 for most rays (2-point RANSAC, then least
    squares on the inliers), and the inlier mask (angular epipolar error below the threshold)."""
    a = np.cross(x1 @ R.T, x2)  # t . a_k = 0
    thr = threshold_deg

    def errors(t: np.ndarray) -> np.ndarray:
        return epipolar_errors_deg(x1, x2, R, t)

    rng = np.random.default_rng(seed)
    best, best_mask = None, np.zeros(len(x1), bool)
    for _ in range(iters if len(x1) >= 2 else 0):
        i, j = rng.choice(len(x1), 2, replace=False)
        t = np.cross(a[i], a[j])
        if np.linalg.norm(t) < 1e-12:
            continue
        mask = errors(_unit(t)) < thr
        if mask.sum() > best_mask.sum():
            best, best_mask = _unit(t), mask
    if best is not None and best_mask.sum() >= 3:
        t = np.linalg.svd(_unit(a[best_mask]))[2][-1]
        mask = errors(t) < thr
        if mask.sum() >= best_mask.sum():
            best, best_mask = t, mask
    return best, best_mask


def epipolar_errors_deg(x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Angles (degrees) between the rays x2 and the epipolar planes of x1 for X2 = R X1 + t."""
    n = np.cross(_unit(t), x1 @ R.T)
    nn = np.linalg.norm(n, axis=1)
    s = np.abs(np.sum(x2 * n, 1)) / np.maximum(nn, 1e-12)
    return np.where(nn > 1e-12, np.degrees(np.arcsin(np.clip(s, 0.0, 1.0))), 0.0)


def triangulated_depth(x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray) -> float | None:
    """Median depth (along the rays of camera 1) of the rays with X2 = R X1 + t (t in metres)."""
    Rx1 = x1 @ R.T
    depths = []
    for u, v in zip(Rx1, x2, strict=True):
        A = np.stack([u, -v], 1)
        lam, *_ = np.linalg.lstsq(A, -t, rcond=None)
        if lam[0] > 0 and lam[1] > 0:
            depths.append(lam[0])
    return float(np.median(depths)) if depths else None


def _rays(cam: pycolmap.Camera, kp: np.ndarray) -> np.ndarray:
    xy = np.asarray(cam.cam_from_img(kp), np.float64)
    return _unit(np.c_[xy, np.ones(len(xy))])


def _check_long_pair(
    x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t_pos: np.ndarray, sigma: float, conf: dict
) -> tuple[str | None, float | None]:
    """(why the pair contradicts the POS or None, the scene depth its consistent inliers give) of a pair
    whose POS baseline is long enough to check: the inliers' rays x1, x2 must fit the POS rotation R
    and baseline t_pos (position noise sigma)."""
    b = float(np.linalg.norm(t_pos))
    _, mask = fit_translation(x1, x2, R, conf["epipolar_deg"], conf["seed"])
    frac = float(mask.mean())
    err = float(np.median(epipolar_errors_deg(x1, x2, R, t_pos)))
    bound = conf["epipolar_deg"] + float(np.degrees(np.arctan(sigma / b)))
    if frac < conf["min_consistent"] or err > bound:
        return (
            f"{100 * frac:.0f}% of the inliers fit the POS rotation; median epipolar error "
            f"{err:.1f} degrees with the POS baseline (max {bound:.1f})"
        ), None
    return None, triangulated_depth(x1[mask], x2[mask], R, t_pos)


def check_pairs(
    db_path: str | Path, records: dict[str, PosRecord], frame: LocalFrame, conf: dict | None = None
) -> dict:
    """Remove the verified pairs that contradict the POS (module docstring) from the database.

    Returns {"checked", "depth_m", "rejected": [{"pair", "inliers", "reason"}]}.
    """
    conf = {**default_conf, **(conf or {})}
    out: dict = {"checked": 0, "depth_m": None, "rejected": []}
    if not conf["check"]:
        return out
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.image_id: im for im in db.read_all_images()}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        kps: dict[int, np.ndarray] = {}
        short, depths = [], []
        pair_ids, geometries = db.read_two_view_geometries()
        for pid, tvg in zip(pair_ids, geometries, strict=True):
            m = np.asarray(tvg.inlier_matches)
            i1, i2 = pycolmap.pair_id_to_image_pair(pid)
            r1, r2 = records.get(images[i1].name), records.get(images[i2].name)
            p1 = None if r1 is None else pose_from_pos(r1, frame)
            p2 = None if r2 is None else pose_from_pos(r2, frame)
            if len(m) < 2 or p1 is None or p2 is None:
                continue
            for i in (i1, i2):
                if i not in kps:
                    kps[i] = np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64)
            x1 = _rays(cams[images[i1].camera_id], kps[i1][m[:, 0]])
            x2 = _rays(cams[images[i2].camera_id], kps[i2][m[:, 1]])
            R = p2[0].T @ p1[0]
            t_pos = p2[0].T @ (p1[1] - p2[1])
            sigma = float(np.hypot(position_sigma(r1, conf), position_sigma(r2, conf)))  # type: ignore[arg-type]
            pair = [images[i1].name, images[i2].name]
            out["checked"] += 1
            if np.linalg.norm(t_pos) <= conf["baseline_sigmas"] * sigma:
                short.append((i1, i2, pair, len(m), x1, x2, R, float(np.linalg.norm(t_pos)), sigma))
                continue
            reason, d = _check_long_pair(x1, x2, R, t_pos, sigma, conf)
            if reason is not None:
                db.delete_two_view_geometry(i1, i2)
                out["rejected"].append({"pair": pair, "inliers": len(m), "reason": reason})
            elif d is not None:
                depths.append(d)
        depth = float(np.median(depths)) if depths else None
        out["depth_m"] = depth
        for i1, i2, pair, n, x1, x2, R, b, sigma in short if depth is not None else []:
            parallax = float(np.median(_angle_deg(x1 @ R.T, x2)))
            bound = conf["max_rotation_deg"] + float(np.degrees(np.arctan((b + 3 * sigma) / (0.5 * depth))))
            if parallax > bound:
                db.delete_two_view_geometry(i1, i2)
                reason = (
                    f"median parallax {parallax:.0f} degrees over a {b:.1f} m POS baseline (max {bound:.0f})"
                )
                out["rejected"].append({"pair": pair, "inliers": n, "reason": reason})
    finally:
        db.close()
    for r in out["rejected"]:
        logger.info("pair %s - %s removed: %s", *r["pair"], r["reason"])
    if out["rejected"]:
        logger.warning(
            "%d of %d verified pairs contradict the POS attitudes and positions (wrong matches): removed",
            len(out["rejected"]),
            out["checked"],
        )
    elif short and depth is None:
        logger.info(
            "%d short-baseline pairs not checked: no scene depth from long-baseline pairs", len(short)
        )
    return out
