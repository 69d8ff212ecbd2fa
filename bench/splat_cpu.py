"""3DGS rasterizer benchmark: forward + backward per step, CPU backend against the plain-PyTorch reference.

    python bench/splat_cpu.py                          # 320x240, 20k Gaussians, 10 steps per backend
    python bench/splat_cpu.py --check                  # exit 1 when a goal of issue 4 is missed
    python bench/splat_cpu.py --gaussians 2000 --width 64 --height 48 --iters 2 --ref-steps 1  # smoke run

Each backend runs in its own subprocess (so that its peak resident memory, ru_maxrss, is its own) on the
same random scene (services/splat/synthetic.py: Gaussians 2-8 m in front of a 60 degree camera, projected
standard deviations 0.5-2.5 px, anisotropic, opacities 0.05-0.95, SH degree 3). A step is projection, SH,
rasterization and the backward pass to every 3D parameter, with torch on `--torch-threads` threads (numba
uses all cores). Timings are medians after a warm-up step; CPU time is user + system of the process, to
tell time spent from time waited on a shared machine. The ratio is the reference's median over the CPU's,
measured in the same run.

Goals (issue 4), printed as PASS / FAIL lines: the CPU backend at least `--min-speedup` (5x) faster than
the reference, and at most `--max-step-ms` (200 ms) per forward + backward step at 320x240 with 20k
Gaussians on 2 cores; the peak memory of both is reported. With `--check` a missed goal exits 1.
"""

from __future__ import annotations

import json
import os
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


GOAL_SIZE = (320, 240, 20_000)  # width, height, Gaussians of the goals
GOAL_CORES = 2


def goals(cpu: dict, ref: dict, min_speedup: float, max_step_ms: float) -> list[tuple[str, bool]]:
    """(line, passed) for each goal of issue 4, from the two backends' figures."""
    ratio = ref["step_ms"] / cpu["step_ms"]
    return [
        (f"speed-up {ratio:.1f}x >= {min_speedup:g}x (reference / cpu, step time)", ratio >= min_speedup),
        (
            f"step {cpu['step_ms']:.1f} ms <= {max_step_ms:g} ms (cpu backend, forward + backward)",
            cpu["step_ms"] <= max_step_ms,
        ),
    ]


def bench(
    n: int = typer.Option(20_000, "--n", "--gaussians", help="number of Gaussians"),
    width: int = typer.Option(320),
    height: int = typer.Option(240),
    steps: int = typer.Option(
        10, "--steps", "--iters", help="timed steps per backend (after a warm-up step)"
    ),
    ref_steps: int = typer.Option(3, help="timed steps of the (slow) reference"),
    torch_threads: int = typer.Option(
        1, help="torch intra-op threads (1 is fastest on a busy 2-core machine)"
    ),
    seed: int = typer.Option(0),
    out: Path | None = typer.Option(None, help="also write the figures to this JSON file"),
    min_speedup: float = typer.Option(5.0, help="goal: reference / cpu step time at least this"),
    max_step_ms: float = typer.Option(200.0, help="goal: cpu forward + backward step at most this (ms)"),
    check: bool = typer.Option(False, "--check", help="exit 1 when a goal is missed"),
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
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 0
    notes = []
    if (width, height, n) != GOAL_SIZE:
        notes.append(f"measured at {width}x{height} with {n} Gaussians; the goals are stated at 320x240, 20k")
    if cores != GOAL_CORES:
        notes.append(f"measured on {cores} cores; the goals are stated for {GOAL_CORES}")
    results = goals(cpu, ref, min_speedup, max_step_ms)
    for line, ok in results:
        console.print(f"[{'green' if ok else 'red'}]{'PASS' if ok else 'FAIL'}[/] {line}")
    console.print(
        f"peak memory (max RSS): cpu {cpu['peak_rss_mb']:.0f} MB "
        f"(+{cpu['peak_rss_mb'] - cpu['base_rss_mb']:.0f} MB over the scene), "
        f"reference {ref['peak_rss_mb']:.0f} MB (+{ref['peak_rss_mb'] - ref['base_rss_mb']:.0f} MB)"
    )
    for note in notes:
        console.print(f"note: {note}")
    if out is not None:
        doc = {
            "rows": rows,
            "ratio": ref["step_ms"] / cpu["step_ms"],
            "cores": cores,
            "goals": [{"goal": line, "pass": ok} for line, ok in results],
            "notes": notes,
        }
        out.write_text(json.dumps(doc, indent=1))
    if check and not all(ok for _, ok in results):
        raise typer.Exit(1)


if __name__ == "__main__":
    typer.run(bench)
