"""3DGS rasterizer benchmark: forward + backward per step, CPU backend against the plain-PyTorch reference.

    python bench/splat_cpu.py                          # 320x240, 20k Gaussians, 10 steps per backend
    python bench/splat_cpu.py --n 50000 --width 640 --height 480

Each backend runs in its own subprocess (so that its peak resident memory, ru_maxrss, is its own) on the
same random scene (services/splat/synthetic.py: Gaussians 2-8 m in front of a 60 degree camera, projected
standard deviations 0.5-2.5 px, anisotropic, opacities 0.05-0.95, SH degree 3). A step is projection, SH,
rasterization and the backward pass to every 3D parameter, with torch on `--torch-threads` threads (numba
uses all cores). Timings are medians after a warm-up step; CPU time is user + system of the process, to
tell time spent from time waited on a shared machine. The ratio is the reference's median over the CPU's,
measured in the same run.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def worker(backend: str, n: int, width: int, height: int, steps: int, torch_threads: int, seed: int) -> dict:
    """Time `steps` forward + backward steps of one backend (in this process)."""
    import numpy as np
    import torch

    from services.splat.backend import rasterization
    from services.splat.projection import pixel_rects
    from services.splat.synthetic import random_scene

    torch.set_num_threads(torch_threads)
    s = random_scene(n, width, height, seed=seed, sh_degree=3)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    fwd, bwd, cpu = [], [], []
    for i in range(steps + 1):
        p = {k: s[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "sh")}
        c0, t0 = _cpu_seconds(), time.perf_counter()
        colors, alphas, info = rasterization(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], s["viewmat"], s["K"], width, height,
            sh_degree=3, backend=backend,
        )  # fmt: skip
        t1 = time.perf_counter()
        loss = (colors * torch.linspace(0.5, 1.5, 3)).mean() + alphas.mean()
        loss.backward()
        t2, c1 = time.perf_counter(), _cpu_seconds()
        if i > 0:  # the first step compiles / warms caches
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            cpu.append(c1 - c0)
    rects = pixel_rects(info["means2d"], info["radii"], width, height).long()
    area = ((rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])).float()
    return {
        "backend": backend,
        "fwd_ms": 1e3 * float(np.median(fwd)),
        "bwd_ms": 1e3 * float(np.median(bwd)),
        "step_ms": 1e3 * float(np.median(np.add(fwd, bwd))),
        "cpu_ms": 1e3 * float(np.median(cpu)),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "base_rss_mb": base_rss,
        "visible": int((info["radii"] > 0).all(-1).sum()),
        "mean_rect_px": float(area[area > 0].mean()),
        "rect_px_per_pixel": float(area.sum()) / (width * height),
        "mean_alpha": float(alphas.mean()),
        "checksum": float(colors.detach().double().sum()),
    }


def bench(
    n: int = typer.Option(20_000, help="number of Gaussians"),
    width: int = typer.Option(320),
    height: int = typer.Option(240),
    steps: int = typer.Option(10, help="timed steps per backend (after one warm-up step)"),
    ref_steps: int = typer.Option(3, help="timed steps of the (slow) reference"),
    torch_threads: int = typer.Option(
        1, help="torch intra-op threads (1 is fastest on a busy 2-core machine)"
    ),
    seed: int = typer.Option(0),
    out: Path | None = typer.Option(None, help="also write the figures to this JSON file"),
    worker_backend: str | None = typer.Option(None, "--worker", hidden=True),
) -> None:
    """Forward + backward per step of the CPU backend and the reference on the same scene."""
    if worker_backend:
        k = steps if worker_backend == "cpu" else ref_steps
        print(json.dumps(worker(worker_backend, n, width, height, k, torch_threads, seed)))
        return
    rows = []
    for be in ("cpu", "reference"):
        cmd = [sys.executable, __file__, "--worker", be, "--n", str(n), "--width", str(width)]
        cmd += ["--height", str(height), "--steps", str(steps), "--ref-steps", str(ref_steps)]
        cmd += ["--torch-threads", str(torch_threads), "--seed", str(seed)]
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    from rich.console import Console
    from rich.table import Table

    cpu, ref = rows
    t = Table(
        title=f"3DGS forward + backward, {width}x{height}, {n} Gaussians (torch threads {torch_threads})"
    )
    for c in (
        "backend",
        "forward ms",
        "backward ms",
        "step ms",
        "CPU ms / step",
        "peak RSS MB",
        "RSS growth MB",
    ):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(
            r["backend"],
            f"{r['fwd_ms']:.1f}",
            f"{r['bwd_ms']:.1f}",
            f"{r['step_ms']:.1f}",
            f"{r['cpu_ms']:.1f}",
            f"{r['peak_rss_mb']:.0f}",
            f"{r['peak_rss_mb'] - r['base_rss_mb']:.0f}",
        )
    console = Console()
    console.print(t)
    console.print(
        f"speed-up (reference / cpu, step time): {ref['step_ms'] / cpu['step_ms']:.1f}x; "
        f"CPU time ratio {ref['cpu_ms'] / cpu['cpu_ms']:.1f}x"
    )
    console.print(
        f"scene: {cpu['visible']} visible Gaussians, mean rectangle {cpu['mean_rect_px']:.0f} px, "
        f"{cpu['rect_px_per_pixel']:.1f} rectangle pixels per image pixel, "
        f"mean alpha {cpu['mean_alpha']:.2f}; "
        f"image checksums cpu {cpu['checksum']:.3f} / reference {ref['checksum']:.3f}"
    )
    if out is not None:
        out.write_text(json.dumps({"rows": rows, "ratio": ref["step_ms"] / cpu["step_ms"]}, indent=1))


if __name__ == "__main__":
    typer.run(bench)
