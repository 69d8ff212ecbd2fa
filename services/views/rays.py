"""Ray and depth-map geometry of the view planners: the paper's viewpoint (equations 3-4), where a ray
meets the sparse points or a plane, depth probes and their read-out."""

from __future__ import annotations

import math

import numpy as np

from services.colmap_model import Camera, Pose
from services.geometry import angle_deg, rot_x


def paper_viewpoint(pose_a: Pose, target: np.ndarray, fraction: float = 0.5) -> tuple[Pose, float]:
    """Equations 3-4: the aerial camera lowered vertically to `fraction` of its height above the target
    and turned about its own x axis until the target is on its principal ray again.

    Returns the new pose and beta (degrees, >= 0), the angle between C_a->T and C_r->T. The rotation is
    R_world_from_cam_r = R_world_from_cam_a @ Rx(theta) with theta = atan2(-d_y, d_z), d the direction
    C_r->T in the old camera frame; for a camera whose x axis is level, d lies in its y-z plane and
    |theta| = beta. Otherwise (a rolled camera) the remaining small rotation that puts T exactly on the
    principal ray is applied too.
    """
    target = np.asarray(target, float)
    C_a = pose_a.center
    C_r = np.array([C_a[0], C_a[1], target[2] + fraction * (C_a[2] - target[2])])
    d = target - C_r
    if np.linalg.norm(d) < 1e-9:
        raise ValueError("the lowered camera coincides with its target")
    Rwc = pose_a.R.T
    d_c = Rwc.T @ (d / np.linalg.norm(d))  # direction to T in the old camera frame
    theta = math.atan2(-d_c[1], d_c[2])
    Rwc_r = Rwc @ rot_x(theta)
    # residual (zero for a camera with a level x axis): rotate the axis onto d exactly
    z_now = Rwc_r[:, 2]
    z_goal = d / np.linalg.norm(d)
    axis = np.cross(z_now, z_goal)
    s, c = float(np.linalg.norm(axis)), float(z_now @ z_goal)
    if s > 1e-12:
        k = axis / s
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        ang = math.atan2(s, c)
        Rwc_r = (np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K) @ Rwc_r
    beta = angle_deg(target - C_a, target - C_r)
    return Pose.from_center(Rwc_r, C_r), beta


def ray_target_points(
    center: np.ndarray,
    direction: np.ndarray,
    points: np.ndarray,
    cone_deg: float = 1.5,
    min_points: int = 3,
    quantile: float = 0.25,
    min_dist: float = 0.0,
    max_dist: float = np.inf,
) -> float | None:
    """Distance along a ray to the first surface, from the sparse points within `cone_deg` of it
    (a low quantile of their distances: points behind the surface are seen from other cameras)."""
    if points is None or len(points) == 0:
        return None
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    v = np.asarray(points, float) - np.asarray(center, float)[None]
    t = v @ d
    r = np.linalg.norm(v - t[:, None] * d[None], axis=1)
    on = (t > max(min_dist, 1e-6)) & (t <= max_dist) & (r <= np.tan(np.radians(cone_deg)) * t)
    if on.sum() < min_points:
        return None
    return float(np.quantile(t[on], quantile))


def ray_plane(center: np.ndarray, direction: np.ndarray, z: float) -> float | None:
    """Distance along a ray to the horizontal plane at height z (None if it does not meet it ahead)."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    if abs(d[2]) < 1e-9:
        return None
    t = (z - center[2]) / d[2]
    return float(t) if t > 0 else None


def probe_camera(camera: Camera, width: int) -> Camera:
    """The camera scaled to `width` pixels (same field of view), for cheap depth probes."""
    s = min(1.0, width / camera.width)
    w, h = max(8, round(camera.width * s)), max(6, round(camera.height * s))
    K = camera.K
    sx, sy = w / camera.width, h / camera.height
    return Camera("PINHOLE", w, h, [K[0, 0] * sx, K[1, 1] * sy, K[0, 2] * sx, K[1, 2] * sy])


def depth_at(depth: np.ndarray, u: int, v: int, window: int = 5, min_valid_div: int = 3) -> float | None:
    """Median valid depth in a `window` x `window` patch around pixel (u, v); None when fewer than
    1/min_valid_div of the patch is valid."""
    r = max(0, window // 2)
    patch = depth[max(0, v - r) : v + r + 1, max(0, u - r) : u + r + 1]
    good = patch[np.isfinite(patch) & (patch > 0)]
    return float(np.median(good)) if good.size >= max(1, patch.size // min_valid_div) else None


def depth_at_center(depth: np.ndarray, window: int = 5) -> float | None:
    """Median valid depth in a window around the image centre (the principal point, for centred K)."""
    h, w = depth.shape
    return depth_at(depth, w // 2, h // 2, window)


def unproject(K: np.ndarray, pose: Pose, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(N, 3) world points at z-depths `z` behind pixels (u, v) (their centres) of a camera (K, pose)."""
    x_cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
    return (x_cam - pose.t[None]) @ pose.R  # R^T (x - t)


def horizontal(v: np.ndarray) -> np.ndarray | None:
    h = np.array([v[0], v[1], 0.0])
    n = np.linalg.norm(h)
    return h / n if n > 1e-6 else None


def carve_ray(
    center: np.ndarray,
    direction: np.ndarray,
    depth_maps: list[tuple[np.ndarray, Pose, np.ndarray]],
    t_min: float,
    t_max: float,
    step: float,
    margin: float,
    free_fraction: float,
    min_views: int,
) -> float | None:
    """The first distance along the ray (center + t direction, t in [t_min, t_max) by `step`) where the
    scene is no longer free space: fewer than `free_fraction` of the depth maps [(K, cam_from_world pose,
    z-depth (H, W), 0 where nothing)] that see the point (at least `min_views`) see `margin` beyond it.
    The maps are the aerial cameras' renders, where a 3DGS trained on them is at its best; a ray from a
    ground camera meets the facade it looks at where they stop seeing through. None: it meets nothing."""
    ts = np.arange(t_min, t_max, step)
    P = center[None] + ts[:, None] * direction[None]
    n_view, n_free = np.zeros(len(ts)), np.zeros(len(ts))
    for K, pose, D in depth_maps:
        uv, z = pose.project(K, P)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 1e-6) & (u >= 0) & (v >= 0) & (u < D.shape[1]) & (v < D.shape[0])
        dd = np.zeros(len(ts))
        dd[ok] = D[v[ok], u[ok]]
        seen = ok & (dd > 0)
        n_view += seen
        n_free += seen & (z < dd - margin)
    hit = np.flatnonzero((n_view >= min_views) & (n_free < free_fraction * n_view))
    return float(ts[hit[0]]) if len(hit) else None
