"""EWA projection of 3D Gaussians to the image plane (plain PyTorch, differentiable).

Conventions (docs/formats.md): camera x right, y down, z forward; `viewmat` is cam_from_world (4, 4);
pixel coordinates follow COLMAP (centre of the top-left pixel at (0.5, 0.5)), so `K` is used as is.
Constants are shared by every backend so that they render the same image.
"""

from __future__ import annotations

import math

import torch

ALPHA_MIN = 1.0 / 255.0  # a Gaussian adds nothing to a pixel where its alpha is below this
ALPHA_MAX = 0.999  # alpha clamp (gsplat's; the 3DGS paper code uses 0.99)
T_MIN = 1e-4  # a pixel stops compositing once its transmittance would fall below this
EPS2D = 0.3  # low-pass filter added to every 2D covariance (pixels^2)
NEAR = 0.01
FAR = 1e10


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(-1, 3, 3)


def covariances(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions and (N, 3) scales (not log) -> (N, 3, 3) covariances R S S R^T."""
    M = quat_to_rotmat(quats) * scales[:, None, :]
    return M @ M.transpose(1, 2)


def jacobian_limits(
    K: torch.Tensor, width: int, height: int, limits: tuple[float, ...] | None = None
) -> tuple[torch.Tensor, ...]:
    """Bounds (x+, x-, y+, y-) on x/z and y/z where the projection's Jacobian is evaluated: a bit beyond
    the frustum, as 3DGS / gsplat clamp it. 0-dim tensors of K's dtype. `limits`: these bounds instead
    (a crop of a larger image renders exactly that image's window with the larger image's bounds)."""
    if limits is not None:
        return tuple(torch.tensor(float(v), dtype=K.dtype) for v in limits)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (
        (width - cx) / fx + 0.3 * tan_x,
        cx / fx + 0.3 * tan_x,
        (height - cy) / fy + 0.3 * tan_y,
        cy / fy + 0.3 * tan_y,
    )


def alpha_reach(opacities: torch.Tensor) -> torch.Tensor:
    """k = 2 ln(o / ALPHA_MIN): alpha = o exp(-q / 2) reaches ALPHA_MIN where the Mahalanobis q <= k
    (k <= 0: never)."""
    return 2.0 * torch.log((opacities / ALPHA_MIN).clamp_min(1e-12))


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
    far: float = FAR,
    eps2d: float = EPS2D,
    limits: tuple[float, ...] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project Gaussians with the local affine (EWA) approximation.

    means (N, 3), quats (N, 4), scales (N, 3) (not log), opacities (N,) in [0, 1], viewmat (4, 4), K (3, 3).
    Returns means2d (N, 2) pixels, conics (N, 3) = upper triangle (a, b, c) of the inverse 2D covariance,
    depths (N,) camera z, radii (N, 2) int32 half extents in pixels of the region where the Gaussian's
    alpha can reach ALPHA_MIN (0 = culled: behind the camera, off-screen or too transparent).
    `limits`: the Jacobian's bounds on x/z, y/z (see jacobian_limits; default: this image's).
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    pc = means @ R.T + t
    z = pc[:, 2]
    in_depth = (z > near) & (z < far)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # safe denominators for culled Gaussians
    x, y = pc[:, 0], pc[:, 1]
    lim_xp, lim_xn, lim_yp, lim_yn = jacobian_limits(K, width, height, limits)
    tx = zs * torch.minimum(torch.maximum(x / zs, -lim_xn), lim_xp)
    ty = zs * torch.minimum(torch.maximum(y / zs, -lim_yn), lim_yp)
    # 2D covariance J W Sigma W^T J^T = T T^T with T = J W R_q S (J: 2x3 Jacobian, W: camera rotation)
    Mt = quat_to_rotmat(quats) * scales[:, None, :]  # R_q S: columns are the scaled principal axes
    Mc = (Mt.transpose(1, 2).reshape(-1, 3) @ R.T).reshape(-1, 3, 3)  # rows: axes in the camera frame
    T0 = (fx / zs)[:, None] * Mc[:, :, 0] - (fx * tx / zs**2)[:, None] * Mc[:, :, 2]
    T1 = (fy / zs)[:, None] * Mc[:, :, 1] - (fy * ty / zs**2)[:, None] * Mc[:, :, 2]
    a = (T0 * T0).sum(-1) + eps2d
    b = (T0 * T1).sum(-1)
    c = (T1 * T1).sum(-1) + eps2d
    det = a * c - b * b
    ok = in_depth & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    with torch.no_grad():
        k = alpha_reach(opacities)  # the bounding box of the ellipse q <= k
        ok = ok & (k > 0)
        k = k.clamp_min(0)
        ext = torch.stack([(k * a.clamp_min(0)).sqrt(), (k * c.clamp_min(0)).sqrt()], -1)
        ext = torch.where(ok[:, None], ext, torch.zeros_like(ext))
        radii = torch.ceil(ext).to(torch.int32)
        m = means2d.detach()
        on_screen = (
            (m[:, 0] + radii[:, 0] > 0)
            & (m[:, 0] - radii[:, 0] < width)
            & (m[:, 1] + radii[:, 1] > 0)
            & (m[:, 1] - radii[:, 1] < height)
        )
        radii = torch.where((ok & on_screen & (radii > 0).all(-1))[:, None], radii, torch.zeros_like(radii))
    return means2d, conics, z, radii


@torch.no_grad()
def frustum_candidates(
    means: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
    far: float = FAR,
    eps2d: float = EPS2D,
    limits: tuple[float, ...] | None = None,
) -> torch.Tensor:
    """Indices (M,) of a superset of the Gaussians `project_gaussians` keeps (radii > 0): in the depth range,
    opaque enough to reach ALPHA_MIN, and with a bound on their screen extent that reaches the image.

    means (N, 3), scales (N, 3) (not log), opacities (N,), viewmat (4, 4), K (3, 3). The bound: a row of the
    2D covariance's factor T = J W R_q S has norm at most f / z * max(scale) * (1 + |x / z|) (the rows of
    W R_q are unit vectors, x / z clamped as in the projection), so a radius is at most
    sqrt(2 ln(o / ALPHA_MIN)) * (that + sqrt(eps2d)) pixels. Projecting only these Gaussians renders the
    same image; an aerial view sees a quarter of an aerial block's Gaussians.
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    pc = means @ R.T + t
    z = pc[:, 2]
    k = alpha_reach(opacities)
    ok = (z > near) & (z < far) & (k > 0)
    zs = torch.where(ok, z, torch.ones_like(z))
    lim_xp, lim_xn, lim_yp, lim_yn = jacobian_limits(K, width, height, limits)
    lim_x, lim_y = float(max(lim_xp, lim_xn)), float(max(lim_yp, lim_yn))
    smax = scales.max(-1).values / zs
    root_k = k.clamp_min(0).sqrt()
    ex = root_k * (fx * smax * (1 + lim_x) + math.sqrt(eps2d)) * 1.01 + 2.0
    ey = root_k * (fy * smax * (1 + lim_y) + math.sqrt(eps2d)) * 1.01 + 2.0
    mx = fx * pc[:, 0] / zs + cx
    my = fy * pc[:, 1] / zs + cy
    ok &= (mx + ex > 0) & (mx - ex < width) & (my + ey > 0) & (my - ey < height)
    return torch.nonzero(ok)[:, 0]


def pixel_rects(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Pixel ranges [x0, x1) x [y0, y1) whose centres lie within `radii` of `means2d`: (N, 4) int32
    (x0, y0, x1, y1), clipped to the image; empty for culled Gaussians. Every backend uses these."""
    m = means2d.detach()
    r = radii.to(m.dtype)
    lo = torch.ceil(m - r - 0.5)
    hi = torch.floor(m + r - 0.5) + 1
    x0 = lo[:, 0].clamp(0, width)
    x1 = hi[:, 0].clamp(0, width)
    y0 = lo[:, 1].clamp(0, height)
    y1 = hi[:, 1].clamp(0, height)
    rects = torch.stack([x0, y0, x1, y1], -1).to(torch.int32)
    empty = (radii <= 0).any(-1) | (rects[:, 2] <= rects[:, 0]) | (rects[:, 3] <= rects[:, 1])
    return torch.where(empty[:, None], torch.zeros_like(rects), rects)


def viewmat_from_pose(R, t, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """cam_from_world rotation (3, 3) and translation (3,) -> (4, 4) viewmat."""
    V = torch.eye(4, dtype=dtype)
    V[:3, :3] = torch.as_tensor(R, dtype=dtype)
    V[:3, 3] = torch.as_tensor(t, dtype=dtype)
    return V


def focal_to_fov(focal: float, pixels: int) -> float:
    return 2 * math.atan(pixels / (2 * focal))
