"""Losses of 3DGS: photometric, (1 - lambda) L1 + lambda (1 - SSIM), lambda = 0.2; the sparse-depth term
(gsplat's simple_trainer `depth_loss`: rendered depth against the SfM points seen by the view); PSNR and
SSIM metrics."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F


@functools.cache
def _window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g


def _blur(x: torch.Tensor, size: int) -> torch.Tensor:
    """(K, H, W) -> the same filtered by the Gaussian window (separable, zero padded): numba on the CPU,
    F.conv2d elsewhere."""
    if x.device.type == "cpu":
        from .cpu import separable_blur_cpu

        return separable_blur_cpu(x, _window(size).to(x))
    return _blur_conv2d(x, size)


def _blur_conv2d(x: torch.Tensor, size: int) -> torch.Tensor:
    """`_blur` by F.conv2d's grouped convolution."""
    g = _window(size).to(x)
    K = x.shape[0]
    wx, wy = g.reshape(1, 1, 1, size).repeat(K, 1, 1, 1), g.reshape(1, 1, size, 1).repeat(K, 1, 1, 1)
    y = F.conv2d(
        F.conv2d(x[None], wx, padding=(0, size // 2), groups=K), wy, padding=(size // 2, 0), groups=K
    )
    return y[0]


def ssim_stats(img: torch.Tensor, size: int = 11) -> torch.Tensor:
    """Windowed mean and mean square of an (H, W, C) image: (2, C, H, W). `ssim`'s second image's part,
    which a trainer computes once per target image."""
    x = torch.stack([img, img * img]).permute(0, 3, 1, 2)
    return _blur(x.reshape(2 * img.shape[-1], *img.shape[:2]), size).reshape(2, img.shape[-1], *img.shape[:2])


def ssim(
    img1: torch.Tensor, img2: torch.Tensor, size: int = 11, stats2: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images in [0, 1] (11x11 Gaussian window, sigma 1.5, zero padding as in
    the 3DGS code). The window is applied separably. `stats2`: `ssim_stats(img2)`, when already known."""
    C = img1.shape[-1]
    mu2, s22 = ssim_stats(img2, size) if stats2 is None else stats2
    x = torch.stack([img1, img1 * img1, img1 * img2]).permute(0, 3, 1, 2)
    mu1, s11, s12 = _blur(x.reshape(3 * C, *img1.shape[:2]), size).reshape(3, C, *img1.shape[:2])
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = s11 - mu1_sq, s22 - mu2_sq, s12 - mu12
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu12 + c1) * (2 * s12 + c2)) / ((mu1_sq + mu2_sq + c1) * (s1 + s2 + c2))
    return m.mean()


def photometric_loss(
    render: torch.Tensor,
    target: torch.Tensor,
    ssim_lambda: float = 0.2,
    target_stats: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """(1 - ssim_lambda) * L1 + ssim_lambda * (1 - SSIM) of (H, W, 3) images; also returns the terms.
    `target_stats`: `ssim_stats(target)`, when already known."""
    l1 = (render - target).abs().mean()
    s = ssim(render, target, stats2=target_stats)
    loss = (1 - ssim_lambda) * l1 + ssim_lambda * (1 - s)
    return loss, {"l1": float(l1.detach()), "ssim": float(s.detach())}


def psnr(render: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (render clamped to [0, 1])."""
    mse = float(((render.clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()


def sample_depth(depth: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of a depth map (H, W) or (H, W, 1) at `pixels` (M, 2), COLMAP pixel coordinates
    (the centre of the top-left pixel at (0.5, 0.5)) -> (M,)."""
    d = depth.reshape(1, 1, depth.shape[0], depth.shape[1])
    H, W = d.shape[-2:]
    size = torch.tensor([W, H], dtype=pixels.dtype, device=pixels.device)
    grid = (pixels / size * 2 - 1).reshape(1, -1, 1, 2).to(d)
    return F.grid_sample(d, grid, mode="bilinear", padding_mode="border", align_corners=False).reshape(-1)


def sparse_depth_loss(
    depth: torch.Tensor, pixels: torch.Tensor, target: torch.Tensor, scene_scale: float
) -> torch.Tensor:
    """L1 in disparity between the rendered expected depth (H, W[, 1]) at `pixels` (M, 2) and the depths
    `target` (M,) of the SfM points there, times `scene_scale` (a relative depth error at the scene's
    distance), as gsplat's simple_trainer does. Pixels where nothing was rendered count as disparity 0."""
    d = sample_depth(depth, pixels)
    disp = torch.where(d > 0, 1.0 / d.clamp_min(1e-6), torch.zeros_like(d))
    return (disp - 1.0 / target).abs().mean() * scene_scale
