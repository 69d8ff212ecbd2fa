"""Gaussian parameters as a `torch.nn.ParameterDict` (the gsplat layout) and their initialisation.

Keys and shapes (N Gaussians, K = (sh_degree + 1)^2 SH coefficients per colour channel):
    means (N, 3), scales (N, 3) log scales, quats (N, 4) (w, x, y, z, any norm),
    opacities (N,) logits, sh0 (N, 1, 3) degree-0 SH, shN (N, K - 1, 3) higher degrees.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from .sh import num_sh_bases, rgb_to_sh

PARAM_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def knn_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """(N, 3) -> (N,) root mean squared distance to the k nearest other points (3DGS's init scale)."""
    k = min(k, len(points) - 1)
    if k < 1:
        return np.ones(len(points))
    d, _ = cKDTree(points).query(points, k=k + 1)
    return np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))


def create_splats(
    points: np.ndarray,
    colors: np.ndarray,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    init_scale: float = 1.0,
) -> torch.nn.ParameterDict:
    """Gaussians at `points` (N, 3) with `colors` (N, 3) in [0, 1] (or uint8): isotropic scales from the
    nearest-neighbour distances, identity rotations, opacity `init_opacity`, SH of degree `sh_degree`
    with only the degree-0 term set."""
    points = np.asarray(points, np.float64)
    colors = np.asarray(colors)
    if colors.dtype == np.uint8:
        colors = colors / 255.0
    dist = np.clip(knn_distance(points) * init_scale, 1e-7, None)
    n = len(points)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    shN = torch.zeros(n, num_sh_bases(sh_degree) - 1, 3)
    params = {
        "means": torch.tensor(points, dtype=torch.float32),
        "scales": torch.log(torch.tensor(dist, dtype=torch.float32))[:, None].repeat(1, 3),
        "quats": quats,
        "opacities": torch.full((n,), math.log(init_opacity / (1 - init_opacity))),
        "sh0": rgb_to_sh(torch.tensor(colors, dtype=torch.float32))[:, None, :],
        "shN": shN,
    }
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in params.items()})


def random_points(n: int, lo: np.ndarray, hi: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n points uniform in the box [lo, hi] with grey colours, for models without SfM points."""
    rng = np.random.default_rng(seed)
    return rng.uniform(lo, hi, (n, 3)), np.full((n, 3), 0.5)


def sh_degree_of(splats: dict[str, torch.Tensor]) -> int:
    """The SH degree stored in `splats` (from the number of coefficients)."""
    return int(round(math.sqrt(splats["shN"].shape[1] + 1))) - 1


def activated(splats: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rasterizer inputs: means, quats, scales (exp), opacities (sigmoid), sh (N, K, 3)."""
    return dict(
        means=splats["means"],
        quats=splats["quats"],
        scales=torch.exp(splats["scales"]),
        opacities=torch.sigmoid(splats["opacities"]),
        sh=torch.cat([splats["sh0"], splats["shN"]], 1),
    )


def splats_from_tensors(
    tensors: dict[str, torch.Tensor], requires_grad: bool = True
) -> torch.nn.ParameterDict:
    return torch.nn.ParameterDict(
        {k: torch.nn.Parameter(tensors[k].detach().clone(), requires_grad=requires_grad) for k in PARAM_KEYS}
    )
