"""3DGS training on CUDA: our trainer (backend "cuda") against gsplat's own training loop, same scene.

    bash scripts/splat_gpu.sh                      # on a GPU machine: pip install gsplat, CUDA tests, this
    python bench/splat_cuda.py                     # renders the synthetic `small` preset first (seed 0)
    python bench/splat_cuda.py --preset tiny --steps 300               # a quick look
    python bench/splat_cuda.py --scene runs/scene                      # a synthetic scene: gt/sparse + images
    python bench/splat_cuda.py --sparse runs/scene-sfm/sparse --images runs/scene/images   # an aerial SfM

Both train on the same views (every 8th aerial image by name held out), at the same resolution, for the
same steps (1000), from the same SfM points, with the same densification schedule: services.splat's
`default` preset (the 3DGS recipe) scaled to the steps by `rescale_schedule`. The reference loop is
gsplat's examples/simple_trainer.py (not in the pip wheel) reduced to its core, written here with gsplat's
public API (`gsplat.rasterization`, `gsplat.DefaultStrategy`): nearest-neighbour scales, random
quaternions, fused Adam per parameter, exponential decay of the means' learning rate,
lerp(L1, 1 - SSIM, 0.2) with `fused_ssim` when installed (else services.splat's SSIM), densification after
the optimizer step. Views come in the same seeded order as our trainer's.

Reported per trainer: seconds per step (the loop alone, after a warm-up that compiles gsplat's kernels),
PSNR / SSIM on the held-out views, the Gaussians at the end, peak GPU memory (torch.cuda.max_memory_allocated
over the run); then ours / gsplat ratios. Exits 0 with a SKIP line when there is no CUDA device or no gsplat.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]


def skip_reason() -> str | None:
    """Why this benchmark cannot run here (None: it can)."""
    import torch

    if not torch.cuda.is_available():
        return "no CUDA device visible to torch"
    if importlib.util.find_spec("gsplat") is None:
        return "gsplat is not installed (pip install gsplat, after torch; see scripts/splat_gpu.sh)"
    return None


def ensure_scene(preset: str, work: Path, seed: int, supersample: int) -> Path:
    """A synthetic survey folder of `preset` under `work` (rendered once, then reused)."""
    from services import synth

    out = work / f"{preset}-seed{seed}-ss{supersample}"
    if (out / "gt" / "sparse").is_dir() and (out / "images").is_dir():
        return out
    t0 = time.perf_counter()
    synth.main(synth.confs[preset], out, seed=seed, supersample=supersample, overwrite=True)
    print(f"rendered the synthetic `{preset}` preset into {out} in {time.perf_counter() - t0:.0f} s")
    return out


def bench_conf(steps: int, max_width: int, seed: int) -> dict[str, Any]:
    """The `default` preset (3DGS) scaled to `steps`, without test renders, one checkpoint at the end."""
    from services.conf import merge_conf
    from services.splat import confs, rescale_schedule

    over = {"max_width": max_width, "seed": seed, "ckpt_every": steps, "keep_ckpts": 1}
    return merge_conf(
        rescale_schedule(confs["default"], steps), {**over, "save_test_renders": False, "log_every": 0}
    )


def view_order(train_ids: list[int], steps: int, seed: int) -> list[int]:
    """The training view of every step: a seeded permutation per epoch, as services.splat.Trainer.view_at."""
    import numpy as np

    out: list[int] = []
    epoch = 0
    while len(out) < steps:
        perm = np.random.default_rng([seed, epoch]).permutation(len(train_ids))
        out += [train_ids[i] for i in perm]
        epoch += 1
    return out[:steps]


def warm_up() -> float:
    """One gsplat forward + backward on a few Gaussians: CUDA context, and gsplat's JIT compile on first
    use (minutes without a prebuilt wheel). Returns its seconds."""
    import gsplat
    import torch

    t0 = time.perf_counter()
    dev = torch.device("cuda")
    g = torch.Generator(device="cpu").manual_seed(0)
    n = 64
    means = (torch.rand(n, 3, generator=g) - 0.5).to(dev) + torch.tensor([0.0, 0.0, 3.0], device=dev)
    means.requires_grad_()
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]], device=dev)
    colors, _, _ = gsplat.rasterization(
        means, torch.rand(n, 4, device=dev), torch.full((n, 3), 0.05, device=dev),
        torch.full((n,), 0.5, device=dev), torch.rand(n, 16, 3, device=dev),
        torch.eye(4, device=dev)[None], K[None], 64, 48, sh_degree=3, packed=False,
    )  # fmt: skip
    colors.sum().backward()
    torch.cuda.synchronize()
    return time.perf_counter() - t0


def _memory_reset() -> None:
    import gc

    import torch

    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()


def _sync() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _peak_mb() -> float:
    import torch

    return torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else float("nan")


def run_ours(data, conf: dict, out: Path, backend: str = "cuda") -> dict[str, Any]:
    """services.splat.Trainer (cuda backend): timing of its loop, held-out metrics, peak memory."""
    from services.splat import Trainer

    _memory_reset()
    tr = Trainer(conf, data, out, backend=backend)
    tr.train(progress=False)
    _sync()
    seconds = float(tr.train_seconds)  # its loop (our history syncs every step), final checkpoint included
    peak = _peak_mb()
    ev = tr.evaluate()
    return {
        "trainer": "ours",
        "seconds": seconds,
        "s_per_step": seconds / conf["steps"],
        "psnr": ev["psnr"],
        "ssim": ev["ssim"],
        "gaussians": len(tr.splats["means"]),
        "peak_gpu_mb": peak,
    }


def _ssim_fn():
    """(name, fn(render (H, W, 3), target (H, W, 3)) -> SSIM): fused_ssim as simple_trainer uses it, else
    services.splat's."""
    try:
        from fused_ssim import fused_ssim

        def fused(a, b):
            return fused_ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], padding="valid")

        return "fused_ssim", fused
    except ImportError:
        from services.splat.loss import ssim

        return "services.splat.loss.ssim (fused_ssim not installed)", ssim


def _knn_scales(points, k: int = 3, chunk: int = 2048):
    """(N, 3) -> (N,) root mean squared distance to the k nearest other points, on the GPU."""
    import torch

    out = []
    for i in range(0, len(points), chunk):
        d = torch.cdist(points[i : i + chunk], points)
        out.append(d.topk(min(k + 1, len(points)), largest=False).values[:, 1:].pow(2).mean(-1).sqrt())
    return torch.cat(out)


def run_gsplat(data, conf: dict, device: str = "cuda") -> dict[str, Any]:
    """gsplat's simple_trainer loop (its core) with `conf`'s steps, learning rates, SH schedule and
    densification: timing, held-out metrics, peak memory."""
    import gsplat
    import torch
    import torch.nn.functional as F

    from services.splat.loss import psnr, ssim
    from services.splat.sh import rgb_to_sh
    from services.splat.train import scene_extent

    dev = torch.device(device)
    _memory_reset()
    torch.manual_seed(conf["seed"])
    steps, lr, sh_degree = int(conf["steps"]), conf["lr"], int(conf["sh_degree"])
    scene_scale = scene_extent([data.views[i] for i in data.train_ids])
    ssim_name, ssim_fn = _ssim_fn()

    # model: simple_trainer's create_splats_with_optimizers (init_type "sfm")
    points = torch.tensor(data.points, dtype=torch.float32, device=dev)
    rgbs = torch.tensor(data.colors, dtype=torch.float32, device=dev)
    n = len(points)
    dist = _knn_scales(points).clamp_min(1e-7) * conf["init_scale"]
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3, device=dev)
    sh[:, 0] = rgb_to_sh(rgbs)
    init_opa = torch.full((n,), float(conf["init_opacity"]), device=dev)
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(points),
            "scales": torch.nn.Parameter(torch.log(dist)[:, None].repeat(1, 3)),
            "quats": torch.nn.Parameter(torch.rand(n, 4, device=dev)),
            "opacities": torch.nn.Parameter(torch.logit(init_opa)),
            "sh0": torch.nn.Parameter(sh[:, :1].clone()),
            "shN": torch.nn.Parameter(sh[:, 1:].clone()),
        }
    )
    rates = {k: lr[k] * (scene_scale if k == "means" else 1.0) for k in params}
    optimizers = {
        k: torch.optim.Adam([{"params": params[k], "lr": rates[k], "name": k}], eps=1e-15, fused=True)
        for k in params
    }
    gamma = (lr["means_final"] / lr["means"]) ** (1.0 / steps)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=gamma)

    # densification: gsplat's DefaultStrategy with our schedule (the fields it has)
    fields = {f.name for f in dataclasses.fields(gsplat.DefaultStrategy)}
    ours = dict(conf["strategy"])
    unsupported = {k: v for k, v in ours.items() if k not in fields and v and k != "verbose"}
    if unsupported:
        print(f"note: gsplat's DefaultStrategy has no {unsupported}: the reference runs without them")
    strategy = gsplat.DefaultStrategy(**{k: v for k, v in ours.items() if k in fields and k != "verbose"})
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=scene_scale)

    pixels = {i: data.views[i].image.to(dev)[None] for i in set(data.train_ids)}
    cams = {
        i: (data.views[i].viewmat.to(dev)[None], data.views[i].K.to(dev)[None])
        for i in range(len(data.views))
    }
    order = view_order(data.train_ids, steps, conf["seed"])

    def render(i: int, degree: int):
        v = data.views[i]
        viewmats, Ks = cams[i]
        colors, alphas, info = gsplat.rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]),
            torch.sigmoid(params["opacities"]), torch.cat([params["sh0"], params["shN"]], 1),
            viewmats, Ks, v.width, v.height, sh_degree=degree, packed=False,
            near_plane=0.01, far_plane=1e10, rasterize_mode="classic",
        )  # fmt: skip
        return colors, alphas, info

    _sync()
    t0 = time.perf_counter()
    for step in range(steps):
        i = order[step]
        colors, _, info = render(i, min(step // conf["sh_degree_interval"], sh_degree))
        strategy.step_pre_backward(params, optimizers, state, step, info)
        l1 = F.l1_loss(colors, pixels[i])
        ssim_loss = 1.0 - ssim_fn(colors[0], pixels[i][0])
        loss = torch.lerp(l1, ssim_loss, conf["ssim_lambda"])
        loss.backward()
        for o in optimizers.values():
            o.step()
            o.zero_grad(set_to_none=True)
        scheduler.step()
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
    _sync()
    seconds = time.perf_counter() - t0
    peak = _peak_mb()

    scores = []
    with torch.no_grad():
        for i in data.test_ids:
            out = render(i, sh_degree)[0][0].clamp(0, 1).cpu()
            scores.append((psnr(out, data.views[i].image), float(ssim(out, data.views[i].image))))
    return {
        "trainer": "gsplat",
        "seconds": seconds,
        "s_per_step": seconds / steps,
        "psnr": sum(s[0] for s in scores) / max(len(scores), 1),
        "ssim": sum(s[1] for s in scores) / max(len(scores), 1),
        "gaussians": len(params["means"]),
        "peak_gpu_mb": peak,
        "ssim_impl": ssim_name,
    }


def bench(
    preset: str = typer.Option("small", help="synthetic preset to render when no --scene / --sparse"),
    scene: Path | None = typer.Option(None, help="a synthetic scene folder (uses gt/sparse and images/)"),
    sparse: Path | None = typer.Option(None, help="a COLMAP model (e.g. the aerial SfM); with --images"),
    images: Path | None = typer.Option(None, help="the image folder of --sparse"),
    prefix: str = typer.Option("aerial/", help="only images whose names start with this"),
    steps: int = typer.Option(1000, help="training steps of each trainer"),
    max_width: int = typer.Option(1500, help="images downsampled to at most this width (both trainers)"),
    seed: int = typer.Option(0),
    supersample: int = typer.Option(1, help="supersampling of the rendered preset (1: quick)"),
    work: Path = typer.Option(ROOT / "runs" / "bench" / "splat_cuda", help="scene cache and outputs"),
    out: Path | None = typer.Option(None, help="also write the figures to this JSON file"),
) -> None:
    """Time `steps` training steps of our cuda trainer and of gsplat's loop on the same scene."""
    reason = skip_reason()
    if reason is not None:
        print(f"SKIP: {reason}; this benchmark needs a CUDA GPU and gsplat (bash scripts/splat_gpu.sh)")
        raise typer.Exit(0)
    if (sparse is None) != (images is None):
        raise typer.BadParameter("--sparse and --images go together")
    import torch

    from services.splat import load_scene

    if sparse is None:
        scene = scene or ensure_scene(preset, work, seed, supersample)
        sparse, images = scene / "gt" / "sparse", scene / "images"
    conf = bench_conf(steps, max_width, seed)
    data = load_scene(sparse, images, max_width, prefix, conf["test_every"])
    v0 = data.views[0]
    s = conf["strategy"]
    import gsplat

    print(
        f"{torch.cuda.get_device_name()}; torch {torch.__version__}, gsplat {gsplat.__version__}\n"
        f"{sparse}: {len(data.train_ids)} training and {len(data.test_ids)} held-out views at "
        f"{v0.width}x{v0.height}, {len(data.points)} points; {steps} steps, SH degree {conf['sh_degree']} "
        f"(+1 every {conf['sh_degree_interval']}), densification every {s['refine_every']} from "
        f"{s['refine_start_iter']} to {s['refine_stop_iter']}, opacity reset every {s['reset_every']}"
    )
    print(f"warm-up (CUDA context, gsplat kernels; a first use compiles them): {warm_up():.1f} s")
    rows = [run_ours(data, conf, work / "ours"), run_gsplat(data, conf)]

    from rich.console import Console
    from rich.table import Table

    t = Table(
        title=f"3DGS training on CUDA, {steps} steps at {v0.width}x{v0.height}: services.splat (ours) "
        "and gsplat's simple_trainer loop"
    )
    for c in ("trainer", "s / step", "steps / s", "held-out PSNR", "SSIM", "Gaussians", "peak GPU MB"):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(
            r["trainer"],
            f"{r['s_per_step']:.4f}",
            f"{1 / r['s_per_step']:.1f}",
            f"{r['psnr']:.2f}",
            f"{r['ssim']:.3f}",
            str(r["gaussians"]),
            f"{r['peak_gpu_mb']:.0f}",
        )
    console = Console()
    console.print(t)
    ours, ref = rows
    ratio = {
        "time": ours["s_per_step"] / ref["s_per_step"],
        "peak_gpu_memory": ours["peak_gpu_mb"] / ref["peak_gpu_mb"],
        "gaussians": ours["gaussians"] / max(ref["gaussians"], 1),
        "psnr_db_difference": ours["psnr"] - ref["psnr"],
    }
    console.print(
        f"ours / gsplat: time per step {ratio['time']:.2f}x, "
        f"peak GPU memory {ratio['peak_gpu_memory']:.2f}x, Gaussians {ratio['gaussians']:.2f}x; "
        f"held-out PSNR {ratio['psnr_db_difference']:+.2f} dB "
        f"(gsplat's SSIM loss: {ref['ssim_impl']})"
    )
    if not all(math.isfinite(r["psnr"]) for r in rows):
        console.print("note: no held-out views (fewer than 2 images?): PSNR is nan")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"rows": rows, "ratio": ratio, "conf": conf}, indent=1, default=str))


if __name__ == "__main__":
    typer.run(bench)
