"""Ground images localized together: a ground-only model from the verified ground-ground matches, placed
in the aerial frame by the 2D-3D correspondences of all its images at once (one similarity, 7 DoF).

The reducer localizes each ground image by its own PnP. With a blurry (CPU-trained) 3DGS the correct
transferred matches of an image often cover one patch of facade: its pose fits them within a pixel and is
still metres off (services.pose_uncertainty). The images of a street see different patches; held together
by their ground-ground matches they pin one similarity far better than each pins its own pose.

    models = ground_models(conf, database, image_dir, ground_names, out_dir)   # ground-only SfM
    result = localize_block(conf, model, correspondences, camera, priors, prior_std)

`correspondences` maps a ground image to the reducer's PnP input: keypoints (N, 2) and their aerial-frame
points (N, 3) (services.transfer writes them to ground_points.npz). The block's scale starts from the POS
(the spread of the ground model's centres against that of their POS), its pose from a generalized
absolute pose LO-RANSAC (pycolmap: the ground model as a rig of cameras); scale, rotation and translation
are then refined together on the inliers (scipy), and each image's camera centre gets a standard deviation
from the similarity's covariance. An image is localized by the block when that deviation is at most
`max_position_std_m` and its pose agrees with its POS as the reducer's poses must.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from services.colmap_model import Camera, Pose

logger = logging.getLogger("midview.ground_block")

default_conf: dict[str, Any] = {
    "enabled": True,
    "min_images": 3,  # a ground-only model of at least this many images
    "min_num_matches": 15,  # ground-ground pairs with fewer verified matches are ignored
    "ransac_px": 6.0,  # generalized absolute pose LO-RANSAC threshold (ground pixels)
    "keep_px": 3.0,  # inliers of the refined similarity
    "min_inliers": 30,  # over the whole block ...
    "min_images_with_inliers": 2,  # ... in at least this many of its images (else it is one image's PnP)
    "min_image_inliers": 6,  # an image counts as one with inliers from this many
    "scale_search": [0.7, 0.85, 1.0, 1.2, 1.4],  # RANSAC at these multiples of the POS scale, the best kept
    "max_scale_change": 0.5,  # the refined scale within this fraction of the POS scale
    "max_position_std_m": 0.25,  # an image's camera centre must be this well determined
    "seed": 0,
    "colmap_log_level": 1,  # glog: 0 info, 1 warnings, 2 errors
}


def ground_models(
    conf: dict, database: Path, image_dir: Path, ground_names: list[str], out_dir: Path
) -> list[pycolmap.Reconstruction]:
    """Incremental SfM of the ground images alone (their verified ground-ground pairs in `database`),
    intrinsics fixed; the models with at least min_images images, largest first."""
    from services.sfm.aerial import colmap_log_level

    o = pycolmap.IncrementalPipelineOptions()
    o.image_names = list(ground_names)
    o.multiple_models = True
    o.min_model_size = int(conf["min_images"])
    o.min_num_matches = int(conf["min_num_matches"])
    o.random_seed = int(conf["seed"])
    o.mapper.random_seed = int(conf["seed"])
    o.extract_colors = False
    o.ba_refine_focal_length = False
    o.ba_refine_extra_params = False
    o.ba_refine_principal_point = False
    o.mapper.abs_pose_refine_focal_length = False
    o.mapper.abs_pose_refine_extra_params = False
    out_dir.mkdir(parents=True, exist_ok=True)
    with colmap_log_level(int(conf["colmap_log_level"])):
        models = pycolmap.incremental_mapping(database, image_dir, out_dir, o)
    keep = [m for m in models.values() if m.num_reg_images() >= int(conf["min_images"])]
    return sorted(keep, key=lambda m: -m.num_reg_images())


def model_poses(model: pycolmap.Reconstruction) -> dict[str, Pose]:
    """cam_from_world of each registered image of a model, by name."""
    out = {}
    for im in model.images.values():
        if im.has_pose:
            m = np.asarray(im.cam_from_world().matrix())
            out[im.name] = Pose(m[:, :3].copy(), m[:, 3].copy())
    return out


def pos_scale(centers: np.ndarray, pos_centers: np.ndarray) -> float | None:
    """Metres per model unit: the RMS spread of the POS centres (n, 3) about their mean over that of the
    model's centres; None for fewer than two images or coincident centres."""
    if len(centers) < 2:
        return None
    sm = float(np.sqrt(np.mean(np.sum((centers - centers.mean(0)) ** 2, 1))))
    sp = float(np.sqrt(np.mean(np.sum((pos_centers - pos_centers.mean(0)) ** 2, 1))))
    return sp / sm if sm > 1e-9 and sp > 1e-9 else None


def _similarity(p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Parameters (7,): rotation vector, translation, log scale -> (s, R, t) of x_model = s R X + t."""
    return float(np.exp(p[6])), Rotation.from_rotvec(p[:3]).as_matrix(), p[3:6]


def block_residuals(
    p: np.ndarray, poses: list[Pose], idx: np.ndarray, kp: np.ndarray, X: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """Reprojection residuals (2N,) of aerial-frame points X (N, 3) in the images poses[idx] (N,) of a
    ground model placed by the similarity p (see _similarity)."""
    s, R, t = _similarity(p)
    xm = s * X @ R.T + t
    out = np.empty((len(X), 2))
    for i in np.unique(idx):
        sel = idx == i
        xc = xm[sel] @ poses[i].R.T + poses[i].t
        uv = xc @ K.T
        z = np.where(np.abs(uv[:, 2]) < 1e-9, 1e-9, uv[:, 2])
        out[sel] = uv[:, :2] / z[:, None] - kp[sel]
    return out.ravel()


def camera_centers(p: np.ndarray, poses: list[Pose]) -> np.ndarray:
    """Aerial-frame centres (n, 3) of the model's cameras under the similarity p."""
    s, R, t = _similarity(p)
    cm = np.array([q.center for q in poses])
    return ((cm - t) / s) @ R


def centre_covariances(p: np.ndarray, cov: np.ndarray, poses: list[Pose], eps: float = 1e-6) -> np.ndarray:
    """Covariances (n, 3, 3) of the aerial-frame camera centres from the similarity's covariance (7, 7)."""
    c0 = camera_centers(p, poses)
    J = np.empty((len(poses), 3, 7))
    for k in range(7):
        dp = np.zeros(7)
        dp[k] = eps
        J[:, :, k] = (camera_centers(p + dp, poses) - c0) / eps
    return J @ cov @ J.transpose(0, 2, 1)


def generalized_pose(
    conf: dict,
    poses: list[Pose],
    scale: float,
    kp: np.ndarray,
    X: np.ndarray,
    idx: np.ndarray,
    camera: Camera,
) -> tuple[np.ndarray, int] | None:
    """Generalized absolute pose LO-RANSAC (pycolmap) of the model scaled by `scale` (metres per unit):
    a rig of cameras, the aerial frame its world. Returns the similarity's parameters (see _similarity)
    and the number of RANSAC inliers, or None."""
    cams_from_rig = [pycolmap.Rigid3d(pycolmap.Rotation3d(q.R), scale * q.t) for q in poses]
    ro = pycolmap.RANSACOptions()
    ro.max_error = float(conf["ransac_px"])
    ro.min_inlier_ratio = 0.05
    ro.max_num_trials = 20000
    ro.random_seed = int(conf["seed"])
    try:
        out = pycolmap.estimate_and_refine_generalized_absolute_pose(
            np.ascontiguousarray(kp, np.float64),
            np.ascontiguousarray(X, np.float64),
            [int(i) for i in idx],
            cams_from_rig,
            [camera.to_pycolmap(1)] * len(poses),
            ro,
        )
    except Exception as e:  # degenerate input
        logger.debug("generalized absolute pose failed: %s", e)
        return None
    if out is None:
        return None
    m = np.asarray(out["rig_from_world"].matrix())
    # x_rig = R X + t and x_model = x_rig / scale
    p = np.concatenate([Rotation.from_matrix(m[:, :3]).as_rotvec(), m[:, 3] / scale, [-np.log(scale)]])
    return p, int(np.sum(out["inlier_mask"]))


def localize_block(
    conf: dict,
    model: pycolmap.Reconstruction,
    correspondences: dict[str, tuple[np.ndarray, np.ndarray]],
    camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, tuple[float, float, float]],
    pnp_conf: dict,
) -> dict[str, Any]:
    """Place one ground-only model in the aerial frame (see the module docstring). Returns a dict with
    `ok`, `reason`, the similarity (scale, R, t: x_model = scale R X + t), inlier counts, and `images`:
    per image its aerial-frame pose (R, t, center), inliers, position_std_m, to_pos and `accepted`."""
    from services.transfer import prior_agreement

    conf = {**default_conf, **(conf or {})}
    poses_by_name = model_poses(model)
    names = sorted(poses_by_name)
    poses = [poses_by_name[n] for n in names]
    res: dict[str, Any] = {"ok": False, "images_in_model": names, "images": {}}
    with_pos = [i for i, n in enumerate(names) if n in priors]
    s0 = pos_scale(
        np.array([poses[i].center for i in with_pos]).reshape(-1, 3),
        np.array([priors[names[i]].center for i in with_pos]).reshape(-1, 3),
    )
    if s0 is None:
        res["reason"] = "fewer than two images with POS"
        return res
    kp_l, X_l, idx_l = [], [], []
    for i, n in enumerate(names):
        if n in correspondences and len(correspondences[n][0]):
            kp_l.append(np.asarray(correspondences[n][0], float).reshape(-1, 2))
            X_l.append(np.asarray(correspondences[n][1], float).reshape(-1, 3))
            idx_l.append(np.full(len(kp_l[-1]), i))
    if not kp_l:
        res["reason"] = "no 2D-3D correspondences in the block"
        return res
    kp, X, idx = np.concatenate(kp_l), np.concatenate(X_l), np.concatenate(idx_l)
    res["num_correspondences"] = int(len(kp))
    if len(kp) < max(int(conf["min_inliers"]), 6):
        res["reason"] = f"{len(kp)} correspondences (< {conf['min_inliers']})"
        return res
    best = None
    for f in conf["scale_search"]:  # the POS scale is approximate: a rig of the wrong scale fits one image
        out = generalized_pose(conf, poses, s0 * float(f), kp, X, idx, camera)
        if out is not None and (best is None or out[1] > best[1]):
            best = out
    if best is None:
        res["reason"] = "generalized absolute pose RANSAC found no pose"
        return res
    p = best[0]
    K = camera.K
    inl = np.linalg.norm(block_residuals(p, poses, idx, kp, X, K).reshape(-1, 2), axis=1) <= conf["ransac_px"]
    for _ in range(3):  # refine scale, rotation and translation together on the inliers
        if inl.sum() < 7:
            break
        fit = least_squares(
            block_residuals,
            p,
            args=(poses, idx[inl], kp[inl], X[inl], K),
            loss="huber",
            f_scale=float(conf["keep_px"]),
            method="trf",
        )
        p = fit.x
        err = np.linalg.norm(block_residuals(p, poses, idx, kp, X, K).reshape(-1, 2), axis=1)
        inl = err <= conf["keep_px"]
    per_image = np.bincount(idx[inl], minlength=len(names))
    n_img = int((per_image >= int(conf["min_image_inliers"])).sum())
    s, R, t = _similarity(p)
    res.update(
        scale=s,
        R=R.tolist(),
        t=t.tolist(),
        pos_scale=1.0 / s0,
        num_inliers=int(inl.sum()),
        images_with_inliers=n_img,
    )
    reasons = []
    if inl.sum() < int(conf["min_inliers"]):
        reasons.append(f"{int(inl.sum())} inliers (< {conf['min_inliers']})")
    if n_img < int(conf["min_images_with_inliers"]):
        reasons.append(f"inliers in {n_img} images (< {conf['min_images_with_inliers']})")
    if abs(np.log(s * s0)) > np.log1p(float(conf["max_scale_change"])):
        reasons.append(f"scale {1 / s:.3f} m per unit, {1 / s0:.3f} from the POS: they disagree")
    r = block_residuals(p, poses, idx[inl], kp[inl], X[inl], K)
    # pixel noise: the inliers' RMS residual distance, at least 1 px
    sigma = max(float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, 1)))), 1.0) if len(r) else 1.0
    J = least_squares(block_residuals, p, args=(poses, idx[inl], kp[inl], X[inl], K), max_nfev=1).jac
    H = J.T @ J
    cov = sigma**2 * np.linalg.inv(H) if np.linalg.cond(H) < 1e15 else np.full((7, 7), np.inf)
    covs = centre_covariances(p, cov, poses) if np.isfinite(cov).all() else None
    res["reason"] = "; ".join(reasons) if reasons else "ok"
    res["ok"] = not reasons
    centers = camera_centers(p, poses)
    for i, n in enumerate(names):
        Ra = poses[i].R @ R
        ta = poses[i].R @ t / s + poses[i].t / s
        pose = Pose(Ra, ta)
        std = float("inf")
        if covs is not None:
            std = float(np.sqrt(max(np.linalg.eigvalsh(covs[i]).max(), 0.0)))
        d = {
            "R": Ra.tolist(),
            "t": ta.tolist(),
            "center": centers[i].tolist(),
            "num_inliers": int(per_image[i]),
            "position_std_m": std,
            "solver": "block",
        }
        why = list(reasons)
        if std > float(conf["max_position_std_m"]):
            why.append(
                f"position ill-determined by the block: std {std:.2f} m (> {conf['max_position_std_m']})"
            )
        if n in priors:
            to_pos, limits, prior_reasons = prior_agreement(pose, priors[n], prior_std.get(n), pnp_conf)
            d.update(to_pos=to_pos, limits=limits)
            why += prior_reasons
        d["accepted"] = not why
        d["reason"] = "; ".join(why) if why else "ok"
        res["images"][n] = d
    return res


def main(
    conf: dict | None,
    database: Path,
    image_dir: Path,
    ground_keypoints: dict[str, np.ndarray],
    points: dict[str, dict[str, np.ndarray]],
    camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, tuple[float, float, float]],
    pnp_conf: dict,
    out_dir: Path,
) -> dict[str, Any]:
    """Localize every ground-only model of the ground images (`ground_keypoints`: name -> keypoints of
    the database) with the reducer's 2D-3D correspondences `points` (services.transfer.read_ground_points).
    Returns {"blocks": [localize_block results], "images": {name: pose dict of the accepted images}}."""
    conf = {**default_conf, **(conf or {})}
    out_dir = Path(out_dir)
    names = sorted(ground_keypoints)
    report: dict[str, Any] = {"blocks": [], "images": {}}
    if not conf["enabled"] or len(names) < int(conf["min_images"]):
        return report
    corr = {
        g: (ground_keypoints[g][np.asarray(d["keypoints"], np.int64)], d["X"])
        for g, d in points.items()
        if g in ground_keypoints and len(d["keypoints"])
    }
    for k, model in enumerate(ground_models(conf, database, image_dir, names, out_dir / "models")):
        r = localize_block(conf, model, corr, camera, priors, prior_std, pnp_conf)
        r["model"] = k
        report["blocks"].append(r)
        accepted = sorted(n for n, d in r["images"].items() if d["accepted"])
        logger.info(
            "ground block %d (%d images): %s; %d/%d correspondences inliers; %d images localized%s",
            k,
            len(r["images_in_model"]),
            r["reason"],
            r.get("num_inliers", 0),
            r.get("num_correspondences", 0),
            len(accepted),
            f" ({', '.join(accepted)})" if accepted else "",
        )
        for n in accepted:
            report["images"].setdefault(n, r["images"][n])
    return report
