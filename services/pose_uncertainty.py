"""How well 2D-3D correspondences determine a camera's position.

A ground image localized on points clustered in a small part of it (a patch of facade) fits them within
a pixel at poses metres apart: a sideways shift trades with a turn. Its covariance tells: the pose's
6x6 covariance from the linearized projection (unit weights, pixel noise sigma), and from it the
standard deviation of the camera centre along its worst direction (and of its attitude about its worst
axis: points far away can leave the centre uncertain and pin the attitude).

    std_m = position_std(pose, camera.K, X, sigma_px=1.0)
    std_m, std_deg = fit_pose_stds(pose, camera.K, kp, X)  # pixel noise: the fit's RMS residual, >= 1 px

Points whose depth comes from a rendered view's surface (lifted by its depth, or triangulated with one
aerial ray, which crosses the view's ray where the view took that pixel's colour) share that surface's
error: all a few percent too near or too far from the view's centre. Scaling points about a centre moves
a camera that sees them along the line from that centre, by the same fraction of its distance: a ground
image placed through a view 50 m away on points 10% too far lands 5 m off, its pixels fitted as well.
`DepthScale` makes each such view's scale a nuisance parameter with a prior:

    std_m, _ = fit_pose_stds(pose, K, kp, X, scale=DepthScale(centres, 0.05))  # NaN rows: independent

For images of a reconstruction whose points are themselves estimated (a run of ground images tied by
their own points), the covariance of the whole bundle adjustment tells instead:

    stds = joint_position_stds(rec, image_ids)  # {image_id: std_m}, the other images held fixed
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from services.colmap_model import Pose


def _skew(v: np.ndarray) -> np.ndarray:
    """(n, 3) vectors -> (n, 3, 3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], 1),
            np.stack([v[:, 2], z, -v[:, 0]], 1),
            np.stack([-v[:, 1], v[:, 0], z], 1),
        ],
        1,
    )


@dataclass(frozen=True)
class DepthScale:
    """The points' shared depth errors: `centres` (n, 3), the centre of the view whose rendered surface
    gave each point its depth (NaN rows: a point independent of any view's surface, e.g. seen by two
    aerial images); the points of one centre scale together about it, by a factor 1 + e with e of
    standard deviation `std` (relative)."""

    centres: np.ndarray
    std: float


def _camera_jacobian(pose: Pose, K: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d(pixel)/d(camera coordinates) (n, 2, 3), camera coordinates (n, 3)) of points X (n, 3)."""
    xc = (pose.R @ (X - pose.center).T).T
    x, y, z = xc[:, 0], xc[:, 1], xc[:, 2]
    fx, fy = K[0, 0], K[1, 1]
    dproj = np.zeros((len(X), 2, 3))
    dproj[:, 0, 0] = fx / z
    dproj[:, 0, 2] = -fx * x / z**2
    dproj[:, 1, 1] = fy / z
    dproj[:, 1, 2] = -fy * y / z**2
    return dproj, xc


def depth_scale_jacobian(pose: Pose, K: np.ndarray, X: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """d(pixel)/d(e) of the projections of points X (n, 3) for each distinct finite row of `centres`
    (n, 3) (a group): X -> C + (1 + e)(X - C) for the points of group C. (2n, groups)."""
    X = np.asarray(X, float).reshape(-1, 3)
    centres = np.asarray(centres, float).reshape(-1, 3)
    finite = np.isfinite(centres).all(1)
    groups = np.unique(centres[finite], axis=0)
    dproj, _ = _camera_jacobian(pose, K, X)
    d_pix = np.einsum("nij,jk,nk->ni", dproj, pose.R, np.where(finite[:, None], X - centres, 0.0))
    E = np.zeros((len(X), 2, len(groups)))
    for k, c in enumerate(groups):
        m = finite & (centres == c).all(1)
        E[m, :, k] = d_pix[m]
    return E.reshape(2 * len(X), len(groups))


def projection_jacobian(pose: Pose, K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """d(pixel)/d(centre, rotation) of the projections of points X (n, 3): (2n, 6). The rotation is a
    small turn w of the camera frame, cam_from_world R = exp([w]x) R."""
    X = np.asarray(X, float).reshape(-1, 3)
    dproj, xc = _camera_jacobian(pose, K, X)
    d_center = np.broadcast_to(-pose.R, (len(X), 3, 3))
    d_rot = -_skew(xc)
    J = np.concatenate([dproj @ d_center, dproj @ d_rot], 2)  # (n, 2, 6)
    return J.reshape(-1, 6)


def pose_covariance(
    pose: Pose, K: np.ndarray, X: np.ndarray, sigma_px: float = 1.0, scale: DepthScale | None = None
) -> np.ndarray:
    """Covariance (6, 6) of (centre in metres, rotation in radians); inf where undetermined. With
    `scale`, each group's depth scale is a nuisance parameter of prior std scale.std, marginalized."""
    J = projection_jacobian(pose, K, X)
    if scale is not None and scale.std > 0:
        E = depth_scale_jacobian(pose, K, X, scale.centres)
        J = np.concatenate([J, E], 1)
    H = J.T @ J
    if scale is not None and scale.std > 0:  # the prior, in units of the pixel noise
        H[6:, 6:] += np.eye(len(H) - 6) * (sigma_px / scale.std) ** 2
    if len(X) < 3 or np.linalg.cond(H) > 1e15:
        return np.full((6, 6), np.inf)
    return sigma_px**2 * np.linalg.inv(H)[:6, :6]


def pose_stds(
    pose: Pose, K: np.ndarray, X: np.ndarray, sigma_px: float = 1.0, scale: DepthScale | None = None
) -> tuple[float, float]:
    """Standard deviations of the camera centre along its least determined direction (m) and of its
    attitude about its least determined axis (degrees); inf where undetermined."""
    cov = pose_covariance(pose, K, X, sigma_px, scale)
    if not np.isfinite(cov).all():
        return float("inf"), float("inf")
    worst = [float(np.sqrt(max(np.linalg.eigvalsh(c).max(), 0.0))) for c in (cov[:3, :3], cov[3:, 3:])]
    return worst[0], float(np.degrees(worst[1]))


def position_std(
    pose: Pose, K: np.ndarray, X: np.ndarray, sigma_px: float = 1.0, scale: DepthScale | None = None
) -> float:
    """Standard deviation (m) of the camera centre along its least determined direction."""
    return pose_stds(pose, K, X, sigma_px, scale)[0]


def fit_pose_stds(
    pose: Pose,
    K: np.ndarray,
    kp: np.ndarray,
    X: np.ndarray,
    min_sigma_px: float = 1.0,
    scale: DepthScale | None = None,
) -> tuple[float, float]:
    """pose_stds with the pixel noise taken from the fit itself: the RMS distance of the points' (n, 3)
    projections to their keypoints kp (n, 2), at least min_sigma_px; inf for fewer than 3 points."""
    X = np.asarray(X, float).reshape(-1, 3)
    if len(X) < 3:
        return float("inf"), float("inf")
    uv, _ = pose.project(K, X)
    sigma = max(float(np.sqrt(np.mean(np.sum((uv - np.asarray(kp, float)) ** 2, 1)))), min_sigma_px)
    return pose_stds(pose, K, X, sigma, scale)


def held_adjustment(
    rec: pycolmap.Reconstruction, free: set[int] | dict[int, str]
) -> tuple[pycolmap.BundleAdjustmentConfig, pycolmap.BundleAdjustmentOptions]:
    """A bundle adjustment of `rec`'s registered images in which only the poses of the images `free` (ids)
    move, with the 3D points; every other pose and all intrinsics held constant."""
    cfg = pycolmap.BundleAdjustmentConfig()
    for iid, im in rec.images.items():
        if not im.has_pose:
            continue
        cfg.add_image(iid)
        if iid not in free:
            cfg.set_constant_rig_from_world_pose(im.frame_id)
    for cid in rec.cameras:
        cfg.set_constant_cam_intrinsics(cid)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = opts.refine_extra_params = opts.refine_principal_point = False
    opts.print_summary = False
    return cfg, opts


def joint_position_stds(
    rec: pycolmap.Reconstruction, image_ids: set[int] | list[int], min_sigma_px: float = 1.0
) -> dict[int, float] | None:
    """Standard deviation (m, along the least determined direction) of the centres of the registered
    images `image_ids` of a reconstruction, from the covariance of its bundle adjustment with every other
    registered image's pose and all intrinsics held constant, the 3D points free.

    Unlike `position_std`, which holds an image's points fixed, this counts what the points themselves
    are worth: a run of ground images tied together by their own points but placed by a few ill-spread
    2D-3D correspondences is as uncertain as those correspondences leave it, however many points its
    images share. The pixel noise of each image is its RMS reprojection error, at least min_sigma_px.
    Returns {image_id: std}, or None when the covariance cannot be computed (a singular problem).
    """
    free = {int(i) for i in image_ids if int(i) in rec.images and rec.images[int(i)].has_pose}
    if not free:
        return {}
    rec = pycolmap.Reconstruction(rec)
    rec.tear_down()  # a copy without the unregistered images (the covariance needs every frame posed)
    for pid in [pid for pid, p in rec.points3D.items() if p.track.length() < 2]:
        rec.delete_point3D(pid)  # a point seen once adds nothing where points are free
    cfg, opts = held_adjustment(rec, free)
    try:
        ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
        cov = pycolmap.estimate_ba_covariance(
            pycolmap.BACovarianceOptions(params=pycolmap.BACovarianceOptionsParams.POSES), rec, ba
        )
    except ValueError:  # COLMAP's checks: an image with no observation left, ...
        return None
    if cov is None:
        return None
    out = {}
    for iid in sorted(free):
        im = rec.images[iid]
        c = cov.get_cam_cov_from_world(iid)  # tangent space of cam_from_world: [rotation, translation]
        if c is None or np.asarray(c).shape != (6, 6) or not np.isfinite(c).all():
            out[iid] = float("inf")
            continue
        c_world = pycolmap.get_covariance_for_inverse(im.cam_from_world(), np.asarray(c))
        res = [
            np.linalg.norm(np.asarray(uv) - p.xy)
            for p in im.points2D
            if p.has_point3D() and (uv := im.project_point(rec.points3D[p.point3D_id].xyz)) is not None
        ]
        sigma = max(float(np.sqrt(np.mean(np.square(res)))) if res else 0.0, min_sigma_px)
        out[iid] = sigma * float(np.sqrt(max(np.linalg.eigvalsh(c_world[3:, 3:]).max(), 0.0)))
    return out
