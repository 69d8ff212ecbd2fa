"""Photometric loss of 3DGS: (1 - lambda) L1 + lambda (1 - SSIM), lambda = 0.2; PSNR and SSIM metrics."""

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


def ssim(img1: torch.Tensor, img2: torch.Tensor, size: int = 11) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images in [0, 1] (11x11 Gaussian window, sigma 1.5, zero padding as in
    the 3DGS code). The window is applied separably."""
    C = img1.shape[-1]
    x = torch.stack([img1, img2, img1 * img1, img2 * img2, img1 * img2]).permute(0, 3, 1, 2)
    x = x.reshape(1, 5 * C, *img1.shape[:2])
    g = _window(size).to(img1)
    wx = g.reshape(1, 1, 1, size).repeat(5 * C, 1, 1, 1)
    wy = g.reshape(1, 1, size, 1).repeat(5 * C, 1, 1, 1)
    y = F.conv2d(
        F.conv2d(x, wx, padding=(0, size // 2), groups=5 * C), wy, padding=(size // 2, 0), groups=5 * C
    )
    mu1, mu2, s11, s22, s12 = y.reshape(5, C, *img1.shape[:2])
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = s11 - mu1_sq, s22 - mu2_sq, s12 - mu12
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu12 + c1) * (2 * s12 + c2)) / ((mu1_sq + mu2_sq + c1) * (s1 + s2 + c2))
    return m.mean()


def photometric_loss(
    render: torch.Tensor, target: torch.Tensor, ssim_lambda: float = 0.2
) -> tuple[torch.Tensor, dict[str, float]]:
    """(1 - ssim_lambda) * L1 + ssim_lambda * (1 - SSIM) of (H, W, 3) images; also returns the terms."""
    l1 = (render - target).abs().mean()
    s = ssim(render, target)
    loss = (1 - ssim_lambda) * l1 + ssim_lambda * (1 - s)
    return loss, {"l1": float(l1.detach()), "ssim": float(s.detach())}


def psnr(render: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (render clamped to [0, 1])."""
    mse = float(((render.clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
