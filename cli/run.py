"""`midview run` (the whole pipeline on a survey, in-process, each stage cached in the job folder) and
`midview demo` (its options; the demo itself is cli/demo.py, its table and report cli/demo_report.py).

Register in cli/main.py:

    from cli import run as run_cli
    app.command("run")(run_cli.run)
    app.command("demo")(run_cli.demo)
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import typer

from cli import demo as demo_mod
from cli.job_options import explain, with_job_options
from services.pipeline import DEFAULT_STAGES, STAGES

logger = logging.getLogger("midview.cli.run")

ROOT = Path(__file__).resolve().parents[1]


def _fail(message: str) -> None:
    typer.secho(message, fg="red", err=True)
    raise typer.Exit(2)


class RichProgress:
    """progress(stage, fraction, message) as a rich progress display, one bar per stage."""

    def __init__(self, stages: list[str]):
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(
            TextColumn("{task.fields[stage]:<13}"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f}%"),
            TimeElapsedColumn(),
            TextColumn("{task.description}"),
        )
        self.tasks = {s: self.progress.add_task("", total=1.0, stage=s, start=False) for s in stages}

    def __enter__(self) -> RichProgress:
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def __call__(self, stage: str, fraction: float, message: str) -> None:
        t = self.tasks.get(stage)
        if t is None:
            return
        if not self.progress.tasks[t].started:
            self.progress.start_task(t)
        self.progress.update(t, completed=fraction, description=message[:60])
        if fraction >= 1.0:
            self.progress.stop_task(t)


def run_job(job, stages: list[str] | None = None, from_stage: str | None = None, force: bool = False) -> dict:
    """Run a job's stages with a rich progress display; returns {stage: marker}."""
    from services import pipeline

    todo = stages or job.options.stages_from(from_stage)
    with RichProgress(list(todo)) as prog:
        return pipeline.run(job, stages=stages, from_stage=from_stage, progress=prog, force=force)


@with_job_options()
def run(
    aerial: Path = typer.Argument(..., help="folder of aerial images"),
    ground: Path = typer.Argument(..., help="folder of ground images"),
    pos: Path = typer.Argument(
        ..., help="POS file (docs/formats.md) naming aerial/... and ground/... images"
    ),
    out: Path = typer.Argument(..., help="job folder (created; a rerun skips finished stages)"),
    cameras: Path | None = typer.Option(None, "--cameras", help="cameras.json (intrinsics per set)"),
    stages: str | None = typer.Option(
        None, help=f"comma-separated stages to run (default: {','.join(DEFAULT_STAGES)})"
    ),
    splat_all: bool = typer.Option(
        False, "--splat-all", help="also train a 3DGS on all images of the combined model (stage splat_all)"
    ),
    from_stage: str | None = typer.Option(None, "--from", help="rerun from this stage on"),
    force: bool = typer.Option(False, help="rerun the --from stage (or every stage) even if up to date"),
    renderer: str = typer.Option("splat", help="splat (3DGS) or gt (ground truth of --scene: benchmarks)"),
    scene: Path | None = typer.Option(None, help="synthetic scene folder, for --renderer gt"),
    torch_threads: int | None = typer.Option(None, help="torch threads (1 is fastest on a busy machine)"),
    splat_set: list[str] = typer.Option(
        [],
        "--splat-set",
        metavar="KEY=VALUE",
        help="3DGS conf entry (services.splat confs), repeatable: --splat-set strategy.max_gaussians=120000",
    ),
    view_set: list[str] = typer.Option(
        [],
        "--view-set",
        metavar="KEY=VALUE",
        help="viewpoint conf entry (services.views), repeatable: --view-set paper.max_width=768",
    ),
    match_set: list[str] = typer.Option(
        [],
        "--match-set",
        metavar="KEY=VALUE",
        help="matching conf entry (services.matching.views, the --matcher's), repeatable:"
        " --match-set render_detection_threshold=-1",
    ),
    render_set: list[str] = typer.Option(
        [],
        "--render-set",
        metavar="KEY=VALUE",
        help="views' rendering conf entry (services.views.rendering), repeatable: --render-set colour=splat",
    ),
    job_options: dict[str, Any] | None = None,
) -> None:
    """Register ground images with aerial images through rendered intermediate views: aerial SfM, 3DGS,
    view planning and rendering, matching, transfer (OUT/transfer/matches.h5, database.db,
    ground_poses.json) and the combined reconstruction (OUT/combined/sparse, report.json)."""
    from pydantic import ValidationError

    from services import pipeline

    stage_list = [s.strip() for s in stages.split(",")] if stages else list(DEFAULT_STAGES)
    if splat_all and "splat_all" not in stage_list:
        stage_list.append("splat_all")
    bad = [s for s in stage_list + ([from_stage] if from_stage else []) if s not in STAGES]
    if bad:
        _fail(f"unknown stage(s) {bad}: stages are {', '.join(STAGES)}")
    if renderer == "gt" and scene is None:
        _fail("--renderer gt needs --scene (a synthetic scene folder)")
    options = {"stages": stage_list, **(job_options or {})}
    try:
        matcher = pipeline.JobOptions.model_validate(options).matcher
    except ValidationError as e:
        _fail(explain(e))
    try:
        overrides = pipeline.parse_settings_overrides(splat_set, view_set, match_set, matcher, render_set)
    except ValueError as e:
        _fail(f"--splat-set / --view-set / --match-set / --render-set: {e}")
    try:
        job = pipeline.Job.create(
            out,
            aerial,
            ground,
            pos,
            cameras,
            options=options,
            settings={
                "renderer": renderer,
                "scene": str(scene) if scene else None,
                "torch_threads": torch_threads,
                **overrides,
            },
        )
    except (FileNotFoundError, ValidationError) as e:
        _fail(str(e))
    t0 = time.perf_counter()
    try:
        results = run_job(job, from_stage=from_stage, force=force)
    except pipeline.StageError as e:
        _fail(str(e))
    typer.echo(
        f"{out}: {sum(not r['skipped'] for r in results.values())} stage(s) run, "
        f"{sum(r['skipped'] for r in results.values())} up to date, {time.perf_counter() - t0:.0f} s"
    )
    if "combined_sfm" in results:
        rep = json.loads((job.combined.report).read_text())
        typer.echo(
            f"combined model: NRI aerial {rep['NRI']['aerial']}, ground {rep['NRI']['ground']}, "
            f"N3P {rep['num_points3D']} -> {job.dir('combined') / 'sparse'}"
        )
        from shared.outcome import job_outcome

        for warning in job_outcome({"combined_sfm": rep})["warnings"]:
            typer.echo(f"warning: {warning}")
        if (rep.get("gis") or {}).get("files"):
            typer.echo(f"GIS outputs ({rep['gis']['crs']}): {job.dir('combined') / 'gis'}")
    if "splat_all" in results:
        m = json.loads((job.splat_all.metrics).read_text())
        typer.echo(
            f"3DGS on all images: {m['num_views']['aerial']} aerial + "
            f"{m['num_views']['ground']} ground views, "
            f"{m['num_gaussians']} Gaussians, held-out PSNR {m['test']['psnr']:.2f} dB "
            f"-> {job.dir('splat_all') / 'point_cloud.ply'}"
        )


# -- demo ------------------------------------------------------------------------------------------
@with_job_options(exclude=frozenset({"seed"}))
def demo(
    out: Path = typer.Argument(Path("runs/demo"), help="output folder (scene/, job/, report.html)"),
    preset: str = typer.Option(
        demo_mod.DEMO_PRESET, help="synthetic preset: isprs (as hard as real ones), small, small-walk, tiny"
    ),
    seed: int = typer.Option(0, help="random seed of the scene and the job"),
    textures: Path | None = typer.Option(
        None, help=f"facade photos (default: {demo_mod.DEFAULT_TEXTURES} if present)"
    ),
    renderer: str = typer.Option("splat", help="splat (3DGS) or gt (the ground-truth upper bound)"),
    deadline: float = typer.Option(
        demo_mod.DEMO_DEADLINE_S / 60,
        help="minutes from the start by which the demo should end: the 3DGS trains for what the stages"
        " before it leave (at most --splat-time-budget; 0: no deadline)",
    ),
    supersample: int = typer.Option(1, help="synthesis supersampling (the preset's is 2: slower, smoother)"),
    baselines: bool = typer.Option(True, help="also run the direct baselines"),
    baseline_sfm: bool = typer.Option(True, help="reconstruct with the baselines' matches too (their NRI)"),
    beside: bool = typer.Option(
        True, help="match the baselines in a second process beside the pipeline (else after it)"
    ),
    job_options: dict[str, Any] | None = None,
) -> None:
    """Synthesize a survey, run midview and the direct baselines on it, print one table (NIM, NCM,
    GT-correct, precision, NMP, NRI of ground images) and write OUT/report.html: the dashboard's page of
    the job, static and self-contained, with that table and match pictures."""
    from pydantic import ValidationError

    from services import pipeline, synth

    if preset not in synth.confs:
        _fail(f"unknown preset {preset!r}: {', '.join(synth.confs)}")
    if deadline < 0:
        _fail(f"--deadline must be >= 0 minutes, got {deadline}")
    options = {**demo_mod.DEMO_OPTIONS, "seed": seed, **(job_options or {})}
    try:
        pipeline.JobOptions.model_validate(options)
    except ValidationError as e:
        _fail(explain(e))
    try:
        demo_mod.run_demo(
            out,
            preset,
            seed,
            textures,
            renderer,
            options,
            supersample,
            baselines,
            baseline_sfm,
            beside,
            run_job,
            deadline * 60 or None,
        )
    except pipeline.StageError as e:
        _fail(str(e))
