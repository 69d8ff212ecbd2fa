"""One entry point for every rasterizer backend, after gsplat's `rasterization` (one camera).

    colors, alphas, info = rasterization(means, quats, scales, opacities, sh, viewmat, K, W, H,
                                         sh_degree=3, backend="cpu")

Backends: "cpu" (numba tile rasterizer), "reference" (plain PyTorch, slow: the test oracle) and "cuda"
(gsplat, needs a CUDA device). `resolve_backend("auto")` picks cuda when torch sees a GPU and gsplat
imports, else cpu.
"""

from __future__ import annotations

import functools
import importlib.util
from typing import Literal

import torch

from .projection import FAR, NEAR, frustum_candidates, project_gaussians
from .sh import spherical_harmonics

Backend = Literal["cpu", "reference", "cuda"]
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


@functools.cache
def gsplat_available() -> bool:
    return importlib.util.find_spec("gsplat") is not None


def resolve_backend(name: str = "auto") -> Backend:
    """ "auto" -> "cuda" if torch.cuda.is_available() and gsplat is importable, else "cpu"."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() and gsplat_available() else "cpu"
    if name not in ("cpu", "reference", "cuda"):
        raise ValueError(f"unknown backend {name!r}: choose auto, cpu, cuda or reference")
    if name == "cuda" and not (torch.cuda.is_available() and gsplat_available()):
        raise RuntimeError("the cuda backend needs a CUDA device and the gsplat package")
    return name  # type: ignore[return-value]


def view_colors(
    means: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor, sh_degree: int | None
) -> torch.Tensor:
    """(N, 3) colours, or SH coefficients (N, K, 3) evaluated towards the camera -> (N, 3) colours >= 0."""
    if sh_degree is None:
        return colors
    campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
    return torch.clamp_min(spherical_harmonics(sh_degree, means - campos, colors) + 0.5, 0.0)


def _full_size(x: torch.Tensor, ids: torch.Tensor, n: int) -> torch.Tensor:
    """Rows of the Gaussians `ids` (M, ...) placed in n rows of zeros (differentiable in x)."""
    return x.new_zeros(n, *x.shape[1:]).index_copy(0, ids, x)


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    backend: str = "cpu",
    near_plane: float = NEAR,
    far_plane: float = FAR,
    limits: tuple[float, ...] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render Gaussians into one pinhole camera.

    means (N, 3), quats (N, 4) (w, x, y, z), scales (N, 3) (not log), opacities (N,) in [0, 1],
    colors (N, 3) or SH coefficients (N, K, 3) with `sh_degree` set, viewmat (4, 4) cam_from_world,
    K (3, 3) in COLMAP pixel convention. render_mode: "RGB", "D" (accumulated z-depth), "ED" (expected
    z-depth: accumulated depth / alpha) or "RGB+D" / "RGB+ED". backgrounds (D,) or None (black).
    Returns render_colors (H, W, D), render_alphas (H, W, 1) and info with "means2d" (N, 2) (call
    `retain_grad` on it before backward to read its gradient), "radii" (N, 2), "depths" (N,), "width",
    "height", "n_cameras". `limits` (CPU backends): the projection's Jacobian bounds of a larger image
    this camera is a crop of (projection.jacobian_limits), so that the crop renders exactly its window.
    """
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}")
    backend = resolve_backend(backend)
    if backend == "cuda":
        from .cuda import rasterization_cuda

        return rasterization_cuda(
            means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree=sh_degree,
            backgrounds=backgrounds, render_mode=render_mode, near_plane=near_plane, far_plane=far_plane,
        )  # fmt: skip
    # project only the Gaussians that can reach the image (the rest get radii 0 and no gradient)
    n = means.shape[0]
    ids = frustum_candidates(
        means, scales, opacities, viewmat, K, width, height, near_plane, far_plane, limits=limits
    )
    sub = ids.numel() < n
    if sub:
        means, quats, scales, opacities, colors = (x[ids] for x in (means, quats, scales, opacities, colors))
    means2d, conics, depths, radii = project_gaussians(
        means, quats, scales, opacities, viewmat, K, width, height, near=near_plane, far=far_plane,
        limits=limits,
    )  # fmt: skip
    rgb = view_colors(means, colors, viewmat, sh_degree) if "RGB" in render_mode else None
    if sub:  # full-size outputs for the caller; the rasterizer reads the 2D means through them
        full_means2d = _full_size(means2d, ids, n)
        means2d = full_means2d[ids]
    d = depths[:, None]
    feats = d if rgb is None else (rgb if render_mode == "RGB" else torch.cat([rgb, d], -1))
    if backend == "reference":
        from .reference import rasterize_reference as raster
    else:
        from .cpu import rasterize_cpu as raster
    out, alphas = raster(means2d, conics, feats, opacities, depths, radii, width, height, backgrounds)
    if render_mode.endswith("ED"):
        out = torch.cat([out[..., :-1], out[..., -1:] / alphas.clamp_min(1e-10)], -1)
    if sub:
        means2d = full_means2d
        depths, conics, radii = (_full_size(x.detach(), ids, n) for x in (depths, conics, radii))
    info = dict(means2d=means2d, radii=radii, depths=depths, conics=conics, width=width, height=height)
    info["n_cameras"] = 1
    return out, alphas, info
