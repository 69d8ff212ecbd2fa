"""`midview run` (the whole pipeline on a survey, in-process, each stage cached in the job folder) and
`midview demo` (a synthetic survey, the pipeline, the direct baselines, one table and report.html: the
dashboard's page of the job, static).

Register in cli/main.py:

    from cli import run as run_cli
    app.command("run")(run_cli.run)
    app.command("demo")(run_cli.demo)
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
import time
from pathlib import Path

import typer

from shared.job_options import DEFAULT_STAGES, STAGES

logger = logging.getLogger("midview.cli.run")

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TEXTURES = ROOT.parent / "shared" / "data" / "lund_street"

# demo settings: chosen so that the `small` preset finishes within 20 minutes on 2 CPU cores
DEMO_OPTIONS = {
    "sfm_features": "sift",
    "matcher": "aliked-lightglue",
    "view_planner": "paper",  # the best single planner (bench/method.py); "both" is better, twice the views
    "views_per_ground_image": 2,
    "splat_steps": 3000,  # 1000 steps: GT-correct 0.6 per pair, 3000: 3.4 (the 3DGS is what limits it)
    "splat_max_width": 400,
    "max_keypoints": 1024,
    "seed": 0,
}
# seconds of 3DGS training at most (services.splat `time_budget_s`): 3000 steps took 8.5-9.5 min on most
# sessions' machines (the baselines' process beside it), 14-17 min on two slower ones, where the demo ran
# 24-30 min; within the budget the run takes fewer steps
DEMO_SPLAT_BUDGET_S = 600.0
DEMO_SETTINGS = {
    "torch_threads": 1,
    # CPU training: cap the model size. 3000 steps at 400 px on small-walk (bench/splat_views.py, 20 views
    # at 1024 px): 120k Gaussians 1.48x the matchable render-truth matches of the bench's default recipe,
    # 60k 1.26x, in 490 s against 412 s of training
    "splat": {"strategy": {"max_gaussians": 120_000}},
    # a quicker aerial SfM: SIFT at 1024 px, spatial matching of 12 neighbours
    "sfm": {
        "features": {"max_image_size": 1024, "max_num_features": 4096},
        "matching": {"exhaustive_max": 0, "num_neighbors": 12},
    },
}


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


def run(
    aerial: Path = typer.Argument(..., help="folder of aerial images"),
    ground: Path = typer.Argument(..., help="folder of ground images"),
    pos: Path = typer.Argument(
        ..., help="POS file (docs/formats.md) naming aerial/... and ground/... images"
    ),
    out: Path = typer.Argument(..., help="job folder (created; a rerun skips finished stages)"),
    cameras: Path | None = typer.Option(None, "--cameras", help="cameras.json (intrinsics per set)"),
    view_planner: str = typer.Option("both", help="paper, ground-aware or both (both: best, most views)"),
    views_per_ground_image: int = typer.Option(2, help="intermediate views per ground image"),
    matcher: str = typer.Option("aliked-lightglue", help="aliked-lightglue or sift"),
    sfm_features: str = typer.Option("sift", help="aerial SfM features: sift or aliked"),
    splat_steps: int = typer.Option(3000, help="3DGS training steps"),
    splat_time_budget: float | None = typer.Option(
        None, help="seconds of 3DGS training at most (fewer steps on a slow machine; default: no limit)"
    ),
    splat_max_width: int = typer.Option(400, help="3DGS training image width"),
    block_steps: int = typer.Option(
        0, help="3DGS steps of each block the views see, at the source resolution (0: no blocks)"
    ),
    block_px: int = typer.Option(
        640, help="block size in pixels of the aerial images at the source resolution"
    ),
    max_keypoints: int = typer.Option(1024, help="keypoints per image for matching"),
    seed: int = typer.Option(0, help="random seed"),
    out_crs: str | None = typer.Option(
        None, "--out-crs", help="CRS of the georeferenced outputs, e.g. EPSG:32633 (default: the POS's)"
    ),
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
    try:
        overrides = pipeline.parse_settings_overrides(splat_set, view_set, match_set, matcher)
    except ValueError as e:
        _fail(f"--splat-set / --view-set / --match-set: {e}")
    try:
        job = pipeline.Job.create(
            out,
            aerial,
            ground,
            pos,
            cameras,
            options={
                "stages": stage_list,
                "sfm_features": sfm_features,
                "matcher": matcher,
                "view_planner": view_planner,
                "views_per_ground_image": views_per_ground_image,
                "splat_steps": splat_steps,
                "splat_time_budget_s": splat_time_budget,
                "splat_max_width": splat_max_width,
                "block_steps": block_steps,
                "block_px": block_px,
                "max_keypoints": max_keypoints,
                "seed": seed,
                "out_crs": out_crs,
            },
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


def baseline_reconstruction(job, label: str, match_file: Path, match_conf: dict, out_dir: Path) -> Path:
    """The combined reconstruction with a direct baseline's matches, by the same procedure as midview's:
    PnP seeds from its matches (aerial keypoints lifted with the aerial model's points), then
    services.sfm.combined. Returns the model folder."""
    from services import reduce
    from services.matching.views import feature_conf
    from services.sfm import combined as combined_sfm

    tdir = out_dir / f"{match_file.stem}-pnp"
    reduce.localize_direct(
        job.transfer_conf(),
        match_file,
        job.sfm.sparse,
        job.pos,
        job.cameras,
        job.sfm.georef,
        tdir,
    )
    fpath = out_dir / "features" / f"{feature_conf(match_conf)['output']}.h5"
    return combined_sfm.main(
        job.combined_conf(),
        job.sfm.dir,
        tdir,
        fpath,
        match_conf,
        job.image_dir,
        job.pos,
        job.cameras,
        out_dir / f"{match_file.stem}-combined",
    )


def direct_baselines(
    scene: Path,
    out_dir: Path,
    aliked_features: dict,
    sift_conf: dict | None = None,
    reuse_features: Path | None = None,
) -> dict[str, tuple]:
    """Direct SIFT and ALIKED+LightGlue (features `aliked_features`, midview's) on the POS pairs.
    `reuse_features`: a feature file of that conf (the job's cache) to start from. Returns {label: (match
    file, matching conf)}."""
    from services.matching import direct
    from services.matching import pairs as pairs_mod
    from shared.images import list_images

    names = list_images(scene / "images")
    pairs = pairs_mod.get_pairs(pairs_mod.confs["pos"], names, scene / "pos.csv", scene / "cameras.json")
    out = {}
    sift = {**direct.confs["sift"], "name": "direct-sift", **(sift_conf or {})}
    out["direct SIFT"] = (
        direct.main(sift, scene, pairs, out_dir / "direct-sift.h5", out_dir / "features"),
        sift,
    )
    alg = {
        **direct.confs["aliked-lightglue"],
        "name": "direct-aliked-lightglue",
        "features": aliked_features,
    }
    # a copy of the job's feature cache: its features are reused, the job's cache stays as it was
    cache = out_dir / "features"
    cache.mkdir(parents=True, exist_ok=True)
    if reuse_features is not None and reuse_features.exists() and not (cache / reuse_features.name).exists():
        shutil.copy2(reuse_features, cache / reuse_features.name)
    out["direct ALIKED+LightGlue"] = (direct.main(alg, scene, pairs, out_dir / "direct-alg.h5", cache), alg)
    return out


def _baselines_process(scene: str, out_dir: str, aliked_features: dict, sift_conf: dict) -> None:
    """direct_baselines in a child process beside the pipeline: one torch thread, its output (logs,
    progress bars, COLMAP's) in OUT_DIR/baselines.log, its result in OUT_DIR/baselines.json."""
    import os

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    log_fd = os.open(out / "baselines.log", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(log_fd, 1)
    os.dup2(log_fd, 2)
    from shared.logging import setup_logging

    setup_logging("INFO")
    import torch

    torch.set_num_threads(1)
    from services.matching import features as features_mod
    from shared.images import list_images

    t0 = time.perf_counter()
    # midview's features first: the demo hands them to the job (BaselinesBeside.share_features)
    features_mod.main(
        aliked_features,
        Path(scene) / "images",
        list_images(Path(scene) / "images"),
        out / "features" / f"{aliked_features['output']}.h5",
    )
    (out / "features" / "shared.done").touch()
    found = direct_baselines(Path(scene), out, aliked_features, sift_conf)
    result = {"found": {k: [str(p), c] for k, (p, c) in found.items()}, "seconds": time.perf_counter() - t0}
    (out / "baselines.json").write_text(json.dumps(result))


class BaselinesBeside:
    """The direct baselines in a spawned child process (no forked torch or numba state) while the pipeline
    runs: on 2 cores the pipeline leaves about half a core idle (single-threaded torch matching, the
    incremental mapper). `wait()` for the result; `stop()` kills the child if it still runs (SIGKILL:
    COLMAP's signal handler can deadlock on SIGTERM). The child extracts midview's features (ALIKED, the
    job's conf) first, which `share_features` hands to the job."""

    def __init__(self, scene: Path, out_dir: Path, aliked_features: dict, sift_conf: dict):
        import multiprocessing

        self.out_dir = Path(out_dir)
        self.log = self.out_dir / "baselines.log"
        self.features = self.out_dir / "features" / f"{aliked_features['output']}.h5"
        (self.out_dir / "baselines.json").unlink(missing_ok=True)
        (self.out_dir / "features" / "shared.done").unlink(missing_ok=True)
        self.proc = multiprocessing.get_context("spawn").Process(
            target=_baselines_process, args=(str(scene), str(out_dir), aliked_features, sift_conf)
        )
        self.proc.start()

    def wait(self, timeout: float | None = None) -> tuple[dict[str, tuple], float]:
        """{label: (match file, matching conf)} as direct_baselines returns, and the child's seconds."""
        self.proc.join(timeout)
        if self.proc.is_alive():
            raise TimeoutError(f"the direct baselines still run after {timeout} s (log: {self.log})")
        result = self.out_dir / "baselines.json"
        if self.proc.exitcode != 0 or not result.exists():
            code = self.proc.exitcode
            raise RuntimeError(f"the direct baselines failed (exit code {code}); see {self.log}")
        r = json.loads(result.read_text())
        return {k: (Path(p), c) for k, (p, c) in r["found"].items()}, float(r["seconds"])

    def share_features(self, dst: Path) -> bool:
        """Copy the child's ALIKED features to `dst` (the job's feature cache) if it has finished them and
        `dst` does not exist; the job extracts whatever they lack. True if copied."""
        if dst.exists() or not (self.out_dir / "features" / "shared.done").exists():
            return False
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_suffix(".part")
        shutil.copy2(self.features, tmp)
        tmp.replace(dst)
        return True

    def stop(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join()


def demo(
    out: Path = typer.Argument(Path("runs/demo"), help="output folder (scene/, job/, report.html)"),
    preset: str = typer.Option("small", help="synthetic preset: tiny, small, small-walk"),
    seed: int = typer.Option(0, help="random seed of the scene and the job"),
    textures: Path | None = typer.Option(
        None, help=f"facade photos (default: {DEFAULT_TEXTURES} if present)"
    ),
    renderer: str = typer.Option("splat", help="splat (3DGS) or gt (the ground-truth upper bound)"),
    view_planner: str = typer.Option(DEMO_OPTIONS["view_planner"], help="paper, ground-aware or both"),
    views_per_ground_image: int = typer.Option(DEMO_OPTIONS["views_per_ground_image"]),
    splat_steps: int = typer.Option(DEMO_OPTIONS["splat_steps"]),
    splat_time_budget: float = typer.Option(
        DEMO_SPLAT_BUDGET_S, help="seconds of 3DGS training at most: fewer steps on a slow machine (0: none)"
    ),
    max_keypoints: int = typer.Option(DEMO_OPTIONS["max_keypoints"]),
    supersample: int = typer.Option(1, help="synthesis supersampling (the preset's is 2: slower, smoother)"),
    baselines: bool = typer.Option(True, help="also run the direct baselines"),
    baseline_sfm: bool = typer.Option(True, help="reconstruct with the baselines' matches too (their NRI)"),
    beside: bool = typer.Option(
        True, help="match the baselines in a second process beside the pipeline (else after it)"
    ),
) -> None:
    """Synthesize a survey, run midview and the direct baselines on it, print one table (NIM, NCM,
    GT-correct, precision, NMP, NRI of ground images) and write OUT/report.html: the dashboard's page of
    the job, static and self-contained, with that table and match pictures."""
    from rich.console import Console

    from services import pipeline, synth
    from services.evaluation import evaluate_matches, evaluate_sfm
    from services.matching.views import feature_conf

    console = Console(width=None if sys.stdout.isatty() else 150)
    t_start = time.perf_counter()
    if preset not in synth.confs:
        _fail(f"unknown preset {preset!r}: {', '.join(synth.confs)}")
    if splat_time_budget < 0:
        _fail(f"--splat-time-budget must be >= 0 seconds, got {splat_time_budget}")
    tex = textures or (DEFAULT_TEXTURES if DEFAULT_TEXTURES.is_dir() else None)
    scene = out / "scene"
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if not synth.scene_complete(scene):
        console.print(f"rendering the {preset} survey into {scene} (textures: {tex})")
        synth.main(
            synth.confs[preset], scene, seed=seed, textures_dir=tex, supersample=supersample, overwrite=True
        )
    timings["synth"] = time.perf_counter() - t0
    options = {
        **DEMO_OPTIONS,
        "seed": seed,
        "view_planner": view_planner,
        "views_per_ground_image": views_per_ground_image,
        "splat_steps": splat_steps,
        "splat_time_budget_s": splat_time_budget or None,
        "max_keypoints": max_keypoints,
    }
    settings = {**DEMO_SETTINGS, "renderer": renderer, "scene": str(scene) if renderer == "gt" else None}
    job = pipeline.Job.create(
        out / "job",
        scene / "images" / "aerial",
        scene / "images" / "ground",
        scene / "pos.csv",
        scene / "cameras.json",
        options=options,
        settings=settings,
    )
    aliked = feature_conf(job.match_conf())
    sift = {"features": _demo_sift_conf()}
    child = None
    if baselines and beside:
        child = BaselinesBeside(scene, out / "baselines", aliked, sift)
        console.print(f"direct baselines beside the pipeline (log: {child.log})")
    files: dict[str, Path] = {}
    sfm_evals: dict[str, dict] = {}
    found: dict[str, tuple] = {}
    try:
        t0 = time.perf_counter()
        todo = list(job.options.stages)
        cut = todo.index("match_views") if child is not None and "match_views" in todo else len(todo)
        results = run_job(job, stages=todo[:cut])
        if cut < len(todo):
            if child.share_features(job.features_path):
                console.print("midview's features: taken from the baselines' process")
            results.update(run_job(job, stages=todo[cut:]))
        timings["pipeline"] = time.perf_counter() - t0
        for s, r in results.items():
            timings[s] = float(r.get("seconds", 0.0))
        if baselines:
            t0 = time.perf_counter()
            with console.status("direct baselines"):
                if child is not None:
                    found, timings["baselines_process"] = child.wait()
                else:
                    pipeline._set_threads(job)
                    found = direct_baselines(scene, out / "baselines", aliked, sift, job.features_path)
            timings["baselines"] = time.perf_counter() - t0  # after the pipeline
    except pipeline.StageError as e:
        _fail(str(e))
    finally:
        if child is not None:  # done, or the pipeline failed: stop the child either way
            child.stop()
    files.update({k: v[0] for k, v in found.items()})
    if baseline_sfm and found:
        t0 = time.perf_counter()
        for label, (path, conf) in found.items():
            with console.status(f"reconstruction with the {label} matches"):
                try:
                    model = baseline_reconstruction(job, label, path, conf, out / "baselines")
                    sfm_evals[label] = evaluate_sfm(scene, model, out / "eval" / f"{path.stem}-combined")
                except Exception as e:  # a baseline that cannot reconstruct reports no NRI
                    logger.warning("no reconstruction with the %s matches: %s", label, e)
        timings["baselines_sfm"] = time.perf_counter() - t0
    files["midview"] = job.transfer.matches
    t0 = time.perf_counter()
    rows = []
    for label, path in files.items():
        s = evaluate_matches(scene, path, out / "eval" / path.stem)
        s["method"] = label
        rows.append(s)
    sfm_evals["midview"] = evaluate_sfm(scene, job.combined.sparse, out / "eval" / "combined")
    timings["evaluation"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    print_table(rows, sfm_evals, console)
    report = write_report_html(out, scene, files, rows, sfm_evals, timings, job)
    console.print(f"report: {report}  (total {timings['total'] / 60:.1f} min)")


def _demo_sift_conf() -> dict:
    """SIFT of the direct baseline for the demo: 4096 features at 1024 px (the bench uses 8192 at 1600)."""
    from services.matching import features as features_mod

    c = json.loads(json.dumps(features_mod.confs["sift"]))
    c["model"]["max_num_features"] = 4096
    c["preprocessing"]["resize_max"] = 1024
    c["output"] = "feats-sift-r1024-k4096"
    return c


def nri_ground(sfm_eval: dict | None) -> str:
    if not sfm_eval:
        return "-"
    g = sfm_eval["per_set"].get("ground", {})
    return f"{g.get('num_registered', 0)}/{g.get('num_gt', 0)}"


def ground_error(sfm_eval: dict | None, key: str = "absolute_error") -> str:
    """Median / max of the ground cameras' position error (`key` of evaluate_sfm's per-set errors)."""
    if not sfm_eval:
        return "-"
    pe = sfm_eval["per_set"].get("ground", {}).get(key, {})
    return "-" if pe.get("median") is None else f"{pe['median']:.2f} / {pe['max']:.2f}"


def ground_within(sfm_eval: dict | None, metres: float = 0.5) -> int:
    """Ground images registered within `metres` of the truth in absolute terms (the georeferenced frame)."""
    if not sfm_eval or not sfm_eval.get("georef"):
        return 0
    rows = sfm_eval.get("per_image") or []
    return sum(r["set"] == "ground" and r.get("absolute_error", float("inf")) <= metres for r in rows)


def print_table(rows: list[dict], sfm_evals: dict[str, dict], console) -> None:
    from rich.table import Table

    table = Table(title="Aerial-ground matching on the co-visible pairs (means per pair)")
    cols = (
        "method",
        "NIM",
        "NCM",
        "GT-correct",
        "precision",
        "pooled prec.",
        "NMP",
        "NRI ground",
        "within 0.5 m",
        "abs err med / max (m)",
        "aerial-aligned (m)",
    )
    for col in cols:
        table.add_column(col, justify="left" if col == "method" else "right")
    for s in rows:
        table.add_row(*row_cells(s, sfm_evals.get(s["method"])))
    console.print(table)
    console.print(
        "NRI ground: ground images registered by the combined reconstruction with each method's matches "
        "(the same procedure); within 0.5 m and abs err: their camera centres' distance to the truth in "
        "the georeferenced frame (what a user gets); aerial-aligned: after aligning the model to the "
        "truth by its aerial cameras alone."
    )


def draw_pair(
    scene: Path, match_file: Path, aerial: str, ground: str, out_path: Path, max_lines: int = 120
) -> Path | None:
    """A side-by-side drawing of the verified matches of one pair (green: GT-correct, red: wrong)."""
    import cv2
    import numpy as np

    from services.evaluation import gt_correct_mask
    from services.evaluation.common import DepthMaps, read_gt_model
    from shared.matchfile import MatchFile

    with MatchFile(match_file) as mf:
        pm = mf.get_pair(aerial, ground)
        if pm is None:
            return None
        inl = np.ones(len(pm.matches), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
        m = pm.matches[inl]
        ka, kg = mf.keypoints(aerial)[m[:, 0]], mf.keypoints(ground)[m[:, 1]]
    cams, poses = read_gt_model(scene)
    with DepthMaps(scene / "gt" / "depth.h5") as d:
        ok = gt_correct_mask(
            ka, kg, cams[aerial], poses[aerial], d[aerial], cams[ground], poses[ground], d[ground]
        )
    ia = cv2.imread(str(scene / "images" / aerial))
    ig = cv2.imread(str(scene / "images" / ground))
    s = ig.shape[0] / ia.shape[0]
    ia = cv2.resize(ia, (round(ia.shape[1] * s), ig.shape[0]))
    canvas = np.concatenate([ia, ig], 1)
    order = np.random.default_rng(0).permutation(len(ka))[:max_lines]
    for i in order:
        p = (int(ka[i, 0] * s), int(ka[i, 1] * s))
        q = (int(kg[i, 0] + ia.shape[1]), int(kg[i, 1]))
        cv2.line(canvas, p, q, (0, 200, 0) if ok[i] else (0, 0, 255), 1, cv2.LINE_AA)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), canvas, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return out_path


def row_cells(s: dict, ev: dict | None) -> list[str]:
    """A method's cells of the demo's table: its match summary (evaluate_matches) and the combined
    reconstruction's ground figures (evaluate_sfm, or None)."""
    return [
        s["method"],
        f"{s['mean_nim']:.1f}",
        f"{s['mean_ncm']:.1f}",
        f"{s['mean_gt_correct']:.1f}",
        f"{s['mean_precision']:.3f}",
        f"{s['pooled_precision']:.3f}",
        f"{s['nmp']}/{s['num_pairs']}",
        nri_ground(ev),
        str(ground_within(ev)) if ev else "-",
        ground_error(ev),
        ground_error(ev, "aerial_aligned_error"),
    ]


def write_report_html(
    out: Path, scene: Path, files: dict, rows: list[dict], sfm_evals: dict[str, dict], timings: dict, job
) -> Path:
    """report.html: the dashboard's page of the job, static and self-contained (cli/report_page.py), with
    the table of every method against the ground truth and match drawings of a few pairs per method."""
    import csv

    from cli.report_page import jpeg_data_url, write_report_page

    # the pairs where midview has most GT-correct matches, drawn for every method
    per_pair = out / "eval" / Path(files["midview"]).stem / "per_pair.csv"
    picks: list[tuple[str, str]] = []
    if per_pair.is_file():
        with open(per_pair) as f:
            rs = sorted(csv.DictReader(f), key=lambda r: -int(r["gt_correct"]))
        picks = [(r["aerial"], r["ground"]) for r in rs[:3]]
    pictures = []
    for a, g in picks:
        for label, path in files.items():
            name = f"{Path(path).stem}__{Path(a).stem}_{Path(g).stem}.jpg"
            p = draw_pair(scene, Path(path), a, g, out / "pictures" / name)
            if p is not None:
                caption = f"{label}: {a} / {g} (green: correct under ground truth, red: wrong)"
                pictures.append({"caption": caption, "src": jpeg_data_url(p, 1400)})
    columns = [
        "method",
        "NIM",
        "NCM",
        "GT-correct",
        "precision",
        "pooled precision",
        "NMP",
        "NRI ground",
        "within 0.5 m",
        "ground abs error med / max (m)",
        "aerial-aligned (m)",
    ]
    table = [row_cells(s, sfm_evals.get(s["method"])) for s in rows]
    notes = [
        f"Synthetic survey {scene}: co-visible aerial-ground pairs of the ground truth, means per pair. "
        "GT-correct: verified matches within 3 px in both images through the true depth; NMP: pairs with "
        "at least 15 GT-correct matches; ground errors in the georeferenced frame (absolute), and after "
        "aligning the aerial cameras to the truth."
    ]
    ev = sfm_evals.get("midview")
    if ev:
        notes.append(
            f"midview's combined SfM: NRI aerial {ev['per_set']['aerial']['num_registered']}/"
            f"{ev['per_set']['aerial']['num_gt']}, ground {nri_ground(ev)}, N3P {ev['num_points3D']}."
        )
    notes.append("Timings (s): " + json.dumps({k: round(v, 1) for k, v in timings.items()}))
    evaluation = {
        "title": "midview and the direct baselines against the ground truth",
        "columns": columns,
        "rows": table,
        "notes": notes,
        "pictures": pictures,
    }
    path = write_report_page(out / "report.html", job, scene, evaluation)
    (out / "report.json").write_text(
        json.dumps({"rows": rows, "sfm": sfm_evals, "timings": timings}, indent=1, default=str)
    )
    return path
