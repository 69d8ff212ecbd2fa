"""A 3DGS training step on the CPU, with and without the trainer's two savings, measured in one run.

    python bench/splat_step.py                      # 400x300, 60k Gaussians spread over 2x the view
    python bench/splat_step.py --spread 1 --steps 5

A step is what the trainer does per image: rasterization (projection, SH, the numba rasterizer), the
photometric loss (L1 and SSIM) against a target image and the backward pass to every 3D parameter.
Variants, interleaved step by step so that they share the machine's state: "trainer" (only the frustum's
candidate Gaussians projected, SSIM's window in numba with the target's half cached, as
services.splat.train does), "no cull" (every Gaussian projected), "conv2d SSIM" (F.conv2d's window, the
target's half recomputed) and "neither" (the trainer before stop 14: the reference of the ratios).
Timings are medians after a warm-up step; the images of all variants are compared.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VARIANTS = ("trainer", "no cull", "conv2d SSIM", "neither")


def bench(
    n: int = typer.Option(60_000, "--n", "--gaussians", help="number of Gaussians"),
    width: int = typer.Option(400),
    height: int = typer.Option(300),
    spread: float = typer.Option(
        2.0, help="Gaussians spread over this many times the view's width and height"
    ),
    steps: int = typer.Option(8, help="timed steps per variant (after a warm-up step)"),
    seed: int = typer.Option(0),
) -> None:
    """Median forward + backward time of a training step per variant, and its ratio to "neither"."""
    import numpy as np
    import torch
    from rich.console import Console
    from rich.table import Table

    import services.splat.backend as backend
    from services.splat import loss
    from services.splat.synthetic import random_scene

    torch.set_num_threads(1)  # as the trainer on the CPU (numba runs the rasterizer on all cores)
    s = random_scene(n, width, height, seed=seed, sigma_px=(0.5, 8.0), sh_degree=1)
    s["means"][:, :2] *= spread
    target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(seed))
    stats = loss.ssim_stats(target)
    cull, blur = backend.frustum_candidates, loss._blur

    def all_ids(means, *a, **k):
        return torch.arange(len(means))

    def step(variant: str) -> tuple[float, float, torch.Tensor, int]:
        backend.frustum_candidates = all_ids if variant in ("no cull", "neither") else cull
        loss._blur = loss._blur_conv2d if variant in ("conv2d SSIM", "neither") else blur
        p = {k: s[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "sh")}
        t0 = time.perf_counter()
        colors, _, info = backend.rasterization(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], s["viewmat"], s["K"], width, height,
            sh_degree=1, backend="cpu",
        )  # fmt: skip
        cached = stats if variant in ("trainer", "no cull") else None
        value, _ = loss.photometric_loss(colors, target, 0.2, cached)
        t1 = time.perf_counter()
        value.backward()
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, colors.detach(), int((info["radii"] > 0).all(-1).sum())

    times: dict[str, list[tuple[float, float]]] = {v: [] for v in VARIANTS}
    images: dict[str, torch.Tensor] = {}
    try:
        for i in range(steps + 1):
            for v in VARIANTS:
                fwd, bwd, img, visible = step(v)
                images[v] = img
                if i > 0:
                    times[v].append((fwd, bwd))
    finally:
        backend.frustum_candidates, loss._blur = cull, blur
    med = {v: np.median(np.array(t), 0) * 1e3 for v, t in times.items()}
    ref = float(med["neither"].sum())
    t = Table(title=f"3DGS training step on the CPU, {width}x{height}, {n} Gaussians ({visible} visible)")
    for c in ("variant", "forward ms", "backward ms", "step ms", "x (neither / variant)"):
        t.add_column(c, justify="right")
    for v in VARIANTS:
        f, b = med[v]
        t.add_row(v, f"{f:.1f}", f"{b:.1f}", f"{f + b:.1f}", f"{ref / (f + b):.2f}")
    console = Console()
    console.print(t)
    diff = max(float((images[v] - images["neither"]).abs().max()) for v in VARIANTS)
    console.print(f"largest pixel difference between the variants' images: {diff:.2e}")


if __name__ == "__main__":
    typer.run(bench)
