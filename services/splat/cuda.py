"""gsplat backend (CUDA only): `rasterization` with the signature of `backend.rasterization`.

gsplat is imported lazily, so this module imports on machines without it. Inputs may live on the CPU:
they are moved to the GPU (autograd follows) and outputs stay there.
"""

from __future__ import annotations

import torch

from .projection import EPS2D, FAR, NEAR


def rasterization_cuda(
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
    near_plane: float = NEAR,
    far_plane: float = FAR,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """One camera through `gsplat.rasterization` (packed=False, classic mode). Returns render_colors
    (H, W, D), render_alphas (H, W, 1) and gsplat's info (means2d (1, N, 2), radii (1, N, ...), ...)."""
    import gsplat

    dev = torch.device("cuda")
    bg = None if backgrounds is None else backgrounds.to(dev).reshape(1, -1)
    colors_out, alphas, info = gsplat.rasterization(
        means.to(dev),
        quats.to(dev),
        scales.to(dev),
        opacities.to(dev),
        colors.to(dev),
        viewmats=viewmat.to(dev, torch.float32)[None],
        Ks=K.to(dev, torch.float32)[None],
        width=width,
        height=height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=EPS2D,
        sh_degree=sh_degree,
        packed=False,
        backgrounds=bg,
        render_mode=render_mode,
        rasterize_mode="classic",
    )
    info.setdefault("width", width)
    info.setdefault("height", height)
    info.setdefault("n_cameras", 1)
    return colors_out[0], alphas[0], info
