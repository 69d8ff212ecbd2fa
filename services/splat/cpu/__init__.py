"""Compiled CPU backend: a tile rasterizer in numba, wrapped in a `torch.autograd.Function`.

    colors, alphas = rasterize_cpu(means2d, conics, colors, opacities, depths, radii, width, height)
    blurred = separable_blur_cpu(x, weights)   # the SSIM window, (K, H, W)

Same inputs, outputs and rules as `services.splat.reference.rasterize_reference`; gradients flow to
means2d, conics, colors and opacities. Kernels compute in float32 (inputs of other dtypes are cast and
gradients cast back). Numba compiles on first use and caches the machine code in __pycache__.
"""

from __future__ import annotations

import os
import threading

import numba
import numba.np.ufunc.parallel as _nb_parallel
import numpy as np
import torch

from ..projection import pixel_rects
from ..reference import depth_order

# numba's default OpenMP threading layer shares its runtime with torch's and leaves torch's element-wise
# ops waiting on busy threads (10 ms per op on a loaded 2-core machine); the workqueue layer does not.
# It must not be entered from two threads at once: `_LOCK` serialises this backend's launches.
if "NUMBA_THREADING_LAYER" not in os.environ and not _nb_parallel._is_initialized:
    numba.config.THREADING_LAYER = "workqueue"
_LOCK = threading.Lock()

from . import kernels  # noqa: E402

TILE = kernels.TILE


def _np32(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().to(torch.float32).numpy())


def _run_parallel(fn, *args):
    """Run a prange kernel (serialised: the workqueue layer is not thread safe)."""
    n_torch = torch.get_num_threads()
    with _LOCK:
        try:
            return fn(*args)
        finally:
            torch.set_num_threads(n_torch)  # the OpenMP layer (if chosen) changes the thread's count


def _tile_order(n_tiles: int) -> np.ndarray:
    """A fixed shuffle of the tiles: numba splits a prange into one contiguous block per thread, and
    neighbouring tiles cost alike (dynamic chunking, numba.set_parallel_chunksize, is slower here)."""
    return np.random.default_rng(0).permutation(n_tiles).astype(np.int64)


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, width, height, backgrounds):
        N, C = colors.shape
        tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
        rects = pixel_rects(means2d, radii, width, height)
        order = depth_order(depths, rects)
        rects_np = rects.numpy()
        offsets, gids = kernels.bin_gaussians(rects_np, order.numpy().astype(np.int64), tiles_x, tiles_y)
        gdata = _np32(torch.cat([means2d, conics, opacities[:, None], colors], 1))
        bg = np.zeros(C, np.float32) if backgrounds is None else _np32(backgrounds.reshape(C))
        order_t = _tile_order(tiles_x * tiles_y)
        out, final_T, last = _run_parallel(
            kernels.rasterize_fwd, gdata, rects_np, gids, offsets, width, height, tiles_x, bg, order_t
        )
        ctx.stash = (gdata, rects_np, gids, offsets, width, height, tiles_x, bg, order_t, final_T, last)
        ctx.dtypes = (means2d.dtype, conics.dtype, colors.dtype, opacities.dtype)
        dt = colors.dtype
        return torch.from_numpy(out).to(dt), torch.from_numpy(1.0 - final_T)[..., None].to(dt)

    @staticmethod
    def backward(ctx, v_colors, v_alphas):
        gdata, rects_np, gids, offsets, width, height, tiles_x, bg, order_t, final_T, last = ctx.stash
        N, C = gdata.shape[0], gdata.shape[1] - 6
        v_c = np.zeros((height, width, C), np.float32) if v_colors is None else _np32(v_colors)
        v_a = np.zeros((height, width), np.float32) if v_alphas is None else _np32(v_alphas[..., 0])
        per_isect = _run_parallel(
            kernels.rasterize_bwd,
            *(gdata, rects_np, gids, offsets, width, height, tiles_x, bg, order_t, final_T, last, v_c, v_a),
        )
        g = torch.from_numpy(kernels.sum_per_gaussian(per_isect, gids, N))
        dm, dco, dcol, dop = ctx.dtypes
        return (
            g[:, 0:2].to(dm),
            g[:, 2:5].to(dco),
            g[:, 6:].to(dcol),
            g[:, 5].to(dop),
            None,
            None,
            None,
            None,
            None,
        )


class _BlurCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weights):
        ctx.weights = _np32(weights)
        out = _run_parallel(kernels.separable_blur, _np32(x), ctx.weights)
        return torch.from_numpy(out).to(x.dtype)

    @staticmethod
    def backward(ctx, v_out):  # a symmetric zero-padded filter is its own adjoint
        v = _run_parallel(kernels.separable_blur, _np32(v_out), ctx.weights)
        return torch.from_numpy(v).to(v_out.dtype), None


def separable_blur_cpu(x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """x (K, H, W) filtered along rows and columns by the symmetric 1D kernel `weights` (odd length), zero
    padded, same size; differentiable in x. Equal to F.conv2d's grouped convolution, ~10x faster here."""
    return _BlurCPU.apply(x, weights)


def rasterize_cpu(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    backgrounds: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Alpha-composite projected Gaussians on the CPU.

    means2d (N, 2), conics (N, 3), colors (N, C), opacities (N,), depths (N,), radii (N, 2) int,
    backgrounds (C,) or None (black). Returns render_colors (H, W, C) and render_alphas (H, W, 1).
    """
    return _RasterizeCPU.apply(means2d, conics, colors, opacities, depths, radii, width, height, backgrounds)


__all__ = ["rasterize_cpu", "separable_blur_cpu"]
