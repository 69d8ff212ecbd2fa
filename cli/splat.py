"""`midview splat`: train a 3D Gaussian Splatting model of a survey and render views of it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

app = typer.Typer(
    help="3D Gaussian Splatting: train on a COLMAP model and its images, render views of the model.",
    no_args_is_help=True,
    add_completion=False,
)


def train_conf(
    preset: dict[str, Any],
    steps: int | None = None,
    options: dict[str, Any] | None = None,
    sets: list[str] | None = None,
) -> dict[str, Any]:
    """The training conf of `midview splat train`: `preset`, its schedule scaled to `steps`
    (services.splat.rescale_schedule), then `options` (dotted key -> value; None: not given), then the
    `--set key=value` strings. Explicit step numbers are taken as given, not scaled. Raises ValueError
    for an unknown key or a value of the wrong kind."""
    from services.conf import merge_conf
    from services.splat import parse_overrides, rescale_schedule
    from services.splat.train import check_conf

    c = rescale_schedule(preset, steps if steps is not None else preset["steps"])
    given = [f"{k}={json.dumps(v)}" for k, v in (options or {}).items() if v is not None]
    for items in (given, list(sets or [])):
        c = merge_conf(c, parse_overrides(items, c))
    if c["steps"] < 1:
        raise ValueError("steps must be >= 1")
    return check_conf(c)


@app.command("train")
def train(
    sparse: Path = typer.Argument(..., help="COLMAP model folder (cameras, images, points3D)"),
    images: Path = typer.Argument(..., help="image folder (names as in the model, e.g. aerial/A0001.jpg)"),
    out: Path = typer.Argument(..., help="output folder: point_cloud.ply, metrics.json, ckpts/, ..."),
    conf: str = typer.Option("auto", help="preset: fast (CPU, minutes), default (3DGS, 30k steps), auto"),
    steps: int | None = typer.Option(
        None, help="training steps (default: the preset's); the preset's schedule is scaled to them"
    ),
    max_width: int | None = typer.Option(None, help="downsample images to at most this width"),
    lr_means: float | None = typer.Option(
        None, help="initial learning rate of the means, times the scene extent (decays to lr.means_final)"
    ),
    lr_scales: float | None = typer.Option(
        None, "--lr-scales", "--lr-scale", help="learning rate of the log scales"
    ),
    refine_start: int | None = typer.Option(None, help="densify from this step (strategy.refine_start_iter)"),
    refine_stop: int | None = typer.Option(None, help="densify until this step (strategy.refine_stop_iter)"),
    refine_every: int | None = typer.Option(None, help="densify every this many steps"),
    reset_every: int | None = typer.Option(None, help="reset the opacities every this many steps"),
    sets: list[str] = typer.Option(
        [],
        "--set",
        metavar="KEY=VALUE",
        help="any conf entry, key=value with dotted keys, e.g. --set strategy.grow_grad2d=0.0004 "
        "--set lr.opacities=0.025 (applied last; see OUT/conf.json for the keys)",
    ),
    backend: str = typer.Option("auto", help="auto, cpu or cuda (auto: cuda when available)"),
    resume: bool = typer.Option(False, "--resume", help="continue from the latest checkpoint in OUT"),
    prefix: str = typer.Option("", help="only images whose names start with this, e.g. aerial/"),
    progress: bool = typer.Option(True, help="show a progress bar"),
) -> None:
    """Train Gaussians on the registered images of SPARSE; every 8th image (by name) is held out and its
    PSNR / SSIM written to OUT/metrics.json."""
    from services.splat import confs, main, resolve_backend

    try:
        be = resolve_backend(backend)
    except (ValueError, RuntimeError) as e:
        typer.secho(str(e), fg="red", err=True)
        raise typer.Exit(2) from e
    name = ("default" if be == "cuda" else "fast") if conf == "auto" else conf
    if name not in confs:
        typer.secho(f"unknown preset {name!r}; choose one of {', '.join(confs)}", fg="red", err=True)
        raise typer.Exit(2)
    if not sparse.is_dir() or not images.is_dir():
        typer.secho(f"{sparse if not sparse.is_dir() else images} is not a folder", fg="red", err=True)
        raise typer.Exit(2)
    options = {
        "max_width": max_width,
        "lr.means": lr_means,
        "lr.scales": lr_scales,
        "strategy.refine_start_iter": refine_start,
        "strategy.refine_stop_iter": refine_stop,
        "strategy.refine_every": refine_every,
        "strategy.reset_every": reset_every,
    }
    try:
        c = train_conf(confs[name], steps, options, sets)
    except ValueError as e:
        typer.secho(str(e), fg="red", err=True)
        raise typer.Exit(2) from e
    main(c, sparse, images, out, backend=be, resume=resume, prefix=prefix, progress=progress)
    m = json.loads((out / "metrics.json").read_text())
    t = m["test"]
    typer.echo(
        f"{out}: {m['num_gaussians']} Gaussians after {m['steps']} steps ({m['seconds']['train']:.0f} s); "
        f"held-out PSNR {t['psnr']:.2f} dB, SSIM {t['ssim']:.3f} on {t['n_views']} views"
    )


@app.command("render")
def render(
    model: Path = typer.Argument(..., help="training folder, checkpoint (.pt) or 3DGS .ply"),
    out: Path = typer.Option(..., "--out", help="output folder: NAME.png per camera (+ depth.h5)"),
    cameras: Path | None = typer.Option(
        None, help="COLMAP model folder or views.json; default: the model folder's training cameras"
    ),
    prefix: str = typer.Option("", help="only cameras whose names start with this"),
    max_width: int | None = typer.Option(None, help="render at most this wide (default: full size)"),
    lower: float | None = typer.Option(
        None,
        help="move each camera down to this fraction of its height above --ground-z, turned to its target",
    ),
    ground_z: float = typer.Option(0.0, help="ground height for --lower"),
    depth: bool = typer.Option(False, "--depth", help="also write expected z-depths to OUT/depth.h5"),
    backend: str = typer.Option("auto", help="auto, cpu or cuda"),
) -> None:
    """Render MODEL into cameras (e.g. the training cameras or a COLMAP model's)."""
    import cv2
    import numpy as np

    from services.colmap_model import Camera, Pose, read_model
    from services.geometry import scaled_intrinsics
    from services.splat import load_model, lowered_pose
    from services.splat import render as render_view

    if cameras is None:
        cameras = (model if model.is_dir() else model.parent) / "views.json"
    if not cameras.exists():
        typer.secho(f"no cameras: {cameras} does not exist (use --cameras)", fg="red", err=True)
        raise typer.Exit(2)
    views: dict[str, tuple[Camera, Pose]] = {}
    if cameras.is_dir():
        cams, poses = read_model(cameras)
        for name in cams:
            views[name] = (cams[name], poses[name])
    else:
        for v in json.loads(cameras.read_text()):
            K = np.array(v["K"])
            cam = Camera("PINHOLE", v["width"], v["height"], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
            views[v["name"]] = (cam, Pose(np.array(v["R"]), np.array(v["t"])))
    views = {k: v for k, v in sorted(views.items()) if k.startswith(prefix)}
    if not views:
        typer.secho(f"no cameras named {prefix}* in {cameras}", fg="red", err=True)
        raise typer.Exit(2)
    splats = load_model(model)
    out.mkdir(parents=True, exist_ok=True)
    depths = {}
    from tqdm import tqdm

    for name, (cam, pose) in tqdm(views.items(), desc="render"):
        K, w, h = scaled_intrinsics(cam.K, cam.width, cam.height, max_width)
        cam = Camera("PINHOLE", w, h, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        if lower is not None:
            pose = lowered_pose(pose, lower, ground_z)
        r = render_view(splats, cam, pose, backend=backend)
        path = out / (str(Path(name).with_suffix("")) + ".png")
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), (r["color"][..., ::-1] * 255).round().astype(np.uint8))
        if depth:
            depths[name] = r["depth"]
    if depth:
        import h5py

        with h5py.File(out / "depth.h5", "w") as f:
            for name, d in depths.items():
                f.create_dataset(name, data=d.astype(np.float32), compression="gzip")
    typer.echo(f"{out}: {len(views)} views")
