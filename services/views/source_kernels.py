"""Compiled per-source scoring of a view's points (services.views.source_colour): one pass over the points
where NumPy made a dozen (projection, bounds, ray angles, incidence, occlusion, penalty). The same
arithmetic as `SourceImages.inside` and `SourceImages.score` for an undistorted (pinhole) source, in float32
where they work in float32."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def score_pinhole(
    X: np.ndarray,
    ray_v: np.ndarray,
    normal: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    centre: np.ndarray,
    pinhole: np.ndarray,
    size: np.ndarray,
    dmap: np.ndarray,
    dscale: float,
    limits: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points X (N, 3) float32 a pinhole source sees: (indices (M,), pixels (M, 2) COLMAP convention,
    penalties (M,), metres per pixel (M,)).

    ray_v (N, 3): the view's unit rays; normal (N, 3) or (0, 3): surface normals (NaN: unknown); R (3, 3),
    t (3,) float32: the source's cam_from_world; centre (3,) float32; pinhole: fx, fy, cx, cy; size: width,
    height; dmap (h, w) float32 or (0, 0): the source's depth map at `dscale` of its pixels (none: no
    occlusion test); limits: cos of max_angle_deg, cos of max_incidence_deg (<= -2: unchecked),
    visibility_rel, visibility_abs_m, mean focal length, resolution_weight_deg."""
    n = X.shape[0]
    idx = np.empty(n, np.int64)
    uv = np.empty((n, 2), np.float32)
    pen = np.empty(n, np.float32)
    gsd = np.empty(n, np.float32)
    fx, fy = np.float32(pinhole[0]), np.float32(pinhole[1])
    cx, cy = np.float32(pinhole[2]), np.float32(pinhole[3])
    w_lim, h_lim = np.float32(size[0] - 1), np.float32(size[1] - 1)
    cos_max, cos_inc = limits[0], limits[1]
    vis_rel, vis_abs = limits[2], limits[3]
    focal, weight = limits[4], limits[5]
    use_normal = normal.shape[0] == n and cos_inc > -2.0
    use_depth = dmap.shape[0] > 0
    dh, dw = dmap.shape[0], dmap.shape[1]
    m = 0
    for i in range(n):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        zc = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
        if not zc > np.float32(1e-3):
            continue
        u = fx * ((R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]) / zc) + cx
        v = fy * ((R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]) / zc) + cy
        if not (u >= 0 and u < w_lim and v >= 0 and v < h_lim):
            continue
        r0, r1, r2 = x0 - centre[0], x1 - centre[1], x2 - centre[2]
        norm = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        cosang = (r0 * ray_v[i, 0] + r1 * ray_v[i, 1] + r2 * ray_v[i, 2]) / norm
        ok = cosang >= cos_max
        if not ok and use_normal:
            ok = -(r0 * normal[i, 0] + r1 * normal[i, 1] + r2 * normal[i, 2]) / norm >= cos_inc  # NaN: False
        if not ok:
            continue
        if use_depth:
            du = min(max(int(u * dscale), 0), dw - 1)
            dv = min(max(int(v * dscale), 0), dh - 1)
            ds = dmap[dv, du]
            if not (ds > 0 and zc <= ds * (1.0 + vis_rel) + vis_abs):
                continue
        idx[m] = i
        uv[m, 0] = u
        uv[m, 1] = v
        g = zc / focal
        gsd[m] = g
        c = min(max(cosang, -1.0), 1.0)
        pen[m] = math.degrees(math.acos(c)) + weight * math.log2(max(g, 1e-6))
        m += 1
    return idx[:m], uv[:m], pen[:m], gsd[:m]
