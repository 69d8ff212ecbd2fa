"""Random Gaussian scenes in front of a camera, for tests and benchmarks."""

from __future__ import annotations

import math

import torch

from .sh import num_sh_bases, rgb_to_sh


def random_camera(width: int, height: int, fov_deg: float = 60.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A pinhole camera at the origin looking along +z: viewmat (4, 4) (identity) and K (3, 3)."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return torch.eye(4), K


def random_scene(
    n: int,
    width: int,
    height: int,
    seed: int = 0,
    sigma_px: tuple[float, float] = (0.5, 2.5),
    depth: tuple[float, float] = (2.0, 8.0),
    sh_degree: int = 0,
    fov_deg: float = 60.0,
) -> dict[str, torch.Tensor]:
    """n Gaussians spread over the view of `random_camera(width, height)`, at z in `depth`, with projected
    standard deviations log-uniform in `sigma_px` pixels (anisotropic, random orientation), opacities
    uniform in [0.05, 0.95] and random colours. Returns a dict of activated tensors: means (N, 3),
    quats (N, 4), scales (N, 3), opacities (N,), sh (N, K, 3) of degree `sh_degree`, viewmat, K."""
    g = torch.Generator().manual_seed(seed)
    viewmat, K = random_camera(width, height, fov_deg)
    f = float(K[0, 0])
    z = depth[0] + (depth[1] - depth[0]) * torch.rand(n, generator=g)
    u = torch.rand(n, generator=g) * (width + 8) - 4
    v = torch.rand(n, generator=g) * (height + 8) - 4
    means = torch.stack([(u - width / 2) * z / f, (v - height / 2) * z / f, z], -1)
    lo, hi = math.log(sigma_px[0]), math.log(sigma_px[1])
    s_px = torch.exp(lo + (hi - lo) * torch.rand(n, 1, generator=g))
    aniso = torch.exp(0.5 * torch.randn(n, 3, generator=g)).clamp(0.3, 3.0)
    scales = s_px * aniso * z[:, None] / f
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    sh = torch.zeros(n, num_sh_bases(sh_degree), 3)
    sh[:, 0] = rgb_to_sh(torch.rand(n, 3, generator=g))
    if sh_degree > 0:
        sh[:, 1:] = 0.3 * torch.randn(n, num_sh_bases(sh_degree) - 1, 3, generator=g)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh, viewmat=viewmat, K=K)
