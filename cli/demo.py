"""The demo (`midview demo`): a synthetic survey, the pipeline in-process, the direct baselines in a
process beside it, one table and report.html (the dashboard's page of the job, static). The command
itself (cli/run.py) only parses its options and calls `run_demo`."""

from __future__ import annotations

import json
import logging
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

logger = logging.getLogger("midview.cli.demo")

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TEXTURES = ROOT.parent / "shared" / "data" / "lund_street"

# the demo's survey: `isprs`, modelled on a real multi-platform survey (60 aerial images of a 5-head oblique
# flight, 20 ground images, facades with depth; 18.6 min on 2 cores); `small` (40 + 15 images, an easier
# survey: flat photo facades) is kept for continuity with earlier figures
DEMO_PRESET = "isprs"

# the demo's job: `midview run`'s, the cpu profile (services.pipeline.PROFILES: SIFT aerial SfM at 1024 px
# with 12 neighbours, paper planner, 2 views per ground image, 3000 3DGS steps at 400 px within a 300 s
# budget and at most 120k Gaussians, 1024 keypoints), ALIKED+LightGlue.
# The profile's 3DGS budget: 3000 steps took 8.5-9.5 min on most sessions' machines (the baselines'
# process beside it), 14-17 min on two slower ones, where the demo ran 24-30 min; within the budget the
# run takes fewer steps (the demo on isprs: 20.6 min with 600 s, the rendering of its views 75 s instead of 5)
DEMO_OPTIONS: dict[str, Any] = {"profile": "cpu", "sfm_features": "sift", "matcher": "aliked-lightglue"}

# the demo's deadline (`--deadline`, seconds from its start): the 3DGS trains for what is left of it once the
# stages before it have run, less the stages after it, estimated as DEMO_AFTER_SPLAT_RATIO times the time
# those before it took (the machine's pace: synthesis and aerial SfM took 3.4-7.0 min in the demos of
# docs/measurements.md, the stages after the 3DGS (views, matching, reduce, combined SfM, the baselines'
# reconstructions, evaluation) 1.2-1.8 times as long, 2.3 on a host that stole a third of the CPU), within
# [DEMO_SPLAT_MIN_S, --splat-time-budget]: on a fast machine the budget alone decides, on a slow one the
# 3DGS gets fewer steps. 15 minutes: on the usual 2-core machine the stages before the 3DGS take about 4 of
# them, so the 3DGS gets its floor and the demo ends in about 14; on one 1.8x slower, in about 18
DEMO_DEADLINE_S = 15 * 60.0
DEMO_AFTER_SPLAT_RATIO = 1.8
DEMO_SPLAT_MIN_S = 180.0  # fewer steps than about 180 s allow on 2 cores give views without detail


def splat_budget_for_deadline(
    elapsed_s: float,
    deadline_s: float,
    cap_s: float | None,
    after_ratio: float = DEMO_AFTER_SPLAT_RATIO,
    floor_s: float = DEMO_SPLAT_MIN_S,
) -> float:
    """Seconds of 3DGS training that end the demo by `deadline_s` when the stages before the 3DGS took
    `elapsed_s` and those after it take `after_ratio` times as long; at least `floor_s`, at most `cap_s`
    (None: no cap)."""
    left = deadline_s - elapsed_s * (1.0 + after_ratio)
    budget = max(floor_s, left)
    return budget if cap_s is None else min(cap_s, budget)


def fit_splat_budget(job, elapsed_s: float, deadline_s: float, console) -> float | None:
    """Set the job's 3DGS time budget for the demo's deadline (job.json keeps it). A 3DGS the job has
    trained, or begun to train (its conf.json), keeps the budget it was trained with, so that a rerun
    neither trains it again nor restarts a killed training."""
    started = job.splat / "conf.json"
    if started.is_file():
        trained = json.loads(started.read_text()).get("time_budget_s")
        budget = float(trained) if trained else None
        reason = "the budget its 3DGS was trained with"
    else:
        budget = splat_budget_for_deadline(elapsed_s, deadline_s, job.options.splat_time_budget_s)
        reason = f"{elapsed_s / 60:.1f} of the deadline's {deadline_s / 60:.1f} min spent"
    job.options = job.options.model_copy(update={"splat_time_budget_s": budget})
    job.save()
    shown = "none" if budget is None else f"{budget:.0f} s"
    console.print(f"3DGS time budget: {shown} ({reason})")
    logger.info("3DGS time budget %s (%s)", shown, reason)
    return budget


# torch on one thread: the baselines' process matches beside the pipeline on the same cores
DEMO_TORCH_THREADS = 1


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
    if job.features_path.name == fpath.name and job.features_path.is_file():
        fpath = job.features_path  # midview's features: the ground pairs' matches cached beside them reused
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


def _baselines_process(
    scene: str, out_dir: str, aliked_features: dict, sift_conf: dict, job_dir: str | None = None
) -> None:
    """direct_baselines in a child process beside the pipeline: one torch thread, its output (logs,
    progress bars, COLMAP's) in OUT_DIR/baselines.log, its result in OUT_DIR/baselines.json. With
    `job_dir`, then the baselines' combined reconstructions (reconstruct_baselines) once the parent says
    the job's aerial model is ready (BaselinesBeside.aerial_model_ready), while the pipeline still runs."""
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
    features = out / "features" / f"{aliked_features['output']}.h5"
    features_mod.main(aliked_features, Path(scene) / "images", list_images(Path(scene) / "images"), features)
    (out / "features" / "shared.done").touch()
    ahead = (
        job_dir is not None and (out / AERIAL_READY).exists() and _match_ground_pairs_ahead(job_dir, features)
    )
    found = direct_baselines(Path(scene), out, aliked_features, sift_conf)
    result: dict = {
        "found": {k: [str(p), c] for k, (p, c) in found.items()},
        "seconds": time.perf_counter() - t0,
    }
    if job_dir is not None and _wait_for(out / AERIAL_READY):
        from services.pipeline import Job

        t1 = time.perf_counter()
        if not ahead:
            _match_ground_pairs_ahead(job_dir, features)
        job, sfm = Job.load(job_dir), {}
        for label, found_one in found.items():  # the cores the pipeline has left, one baseline at a time
            if (out / PIPELINE_DONE).exists() and torch.get_num_threads() != (os.cpu_count() or 1):
                logger.info("the pipeline is done: the baselines take every core")
                torch.set_num_threads(os.cpu_count() or 1)
            sfm.update(reconstruct_baselines(job, {label: found_one}, Path(scene), out.parent, _LogConsole()))
        result.update(sfm=sfm, sfm_seconds=time.perf_counter() - t1)
    (out / "baselines.json").write_text(json.dumps(result, default=_plain))


def _plain(o):
    """JSON for what evaluate_sfm's reports hold besides plain types: numpy values and arrays, paths."""
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


AERIAL_READY = "aerial-model.ready"  # the parent's word to the child: the job's aerial model is done
PIPELINE_DONE = "pipeline.done"  # ... and the pipeline is done: the child may use every core


def _wait_for(flag: Path, poll_s: float = 1.0) -> bool:
    """Wait until `flag` exists; False if the parent process went away first."""
    import os

    parent = os.getppid()
    while not flag.exists():
        if os.getppid() != parent:
            return False
        time.sleep(poll_s)
    return True


class _LogConsole:
    """The few rich Console calls reconstruct_baselines makes, to the log (the child has no terminal)."""

    def status(self, message: str):
        import contextlib

        logger.info("%s", message)
        return contextlib.nullcontext()


class BaselinesBeside:
    """The direct baselines in a spawned child process (no forked torch or numba state) while the pipeline
    runs: on 2 cores the pipeline leaves about half a core idle (single-threaded torch matching, the
    incremental mapper). `wait()` for the result; `stop()` kills the child if it still runs (SIGKILL:
    COLMAP's signal handler can deadlock on SIGTERM). The child extracts midview's features (ALIKED, the
    job's conf) first, which `share_features` hands to the job."""

    def __init__(
        self, scene: Path, out_dir: Path, aliked_features: dict, sift_conf: dict, job_dir: Path | None = None
    ):
        import multiprocessing

        self.out_dir = Path(out_dir)
        self.log = self.out_dir / "baselines.log"
        self.features = self.out_dir / "features" / f"{aliked_features['output']}.h5"
        self.sfm: dict[str, dict] | None = None  # the baselines' reconstructions, when the child made them
        self.sfm_seconds = 0.0
        for stale in ("baselines.json", "features/shared.done", AERIAL_READY, PIPELINE_DONE):
            (self.out_dir / stale).unlink(missing_ok=True)
        job = None if job_dir is None else str(job_dir)
        self.proc = multiprocessing.get_context("spawn").Process(
            target=_baselines_process, args=(str(scene), str(out_dir), aliked_features, sift_conf, job)
        )
        self.proc.start()

    def aerial_model_ready(self) -> None:
        """Tell the child that the job's aerial model is done: it reconstructs the baselines after its
        matching (if it was given the job)."""
        flag = self.out_dir / AERIAL_READY
        if not flag.exists():
            self.out_dir.mkdir(parents=True, exist_ok=True)
            flag.touch()

    def pipeline_done(self) -> None:
        """Tell the child that the pipeline is done: its reconstructions still to come use every core."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        (self.out_dir / PIPELINE_DONE).touch()

    def wait(self, timeout: float | None = None) -> tuple[dict[str, tuple], float]:
        """{label: (match file, matching conf)} as direct_baselines returns, and the child's seconds; the
        child's reconstructions, if it made them, in `sfm` ({label: evaluate_sfm}) and `sfm_seconds`."""
        self.proc.join(timeout)
        if self.proc.is_alive():
            raise TimeoutError(f"the direct baselines still run after {timeout} s (log: {self.log})")
        result = self.out_dir / "baselines.json"
        if self.proc.exitcode != 0 or not result.exists():
            code = self.proc.exitcode
            raise RuntimeError(f"the direct baselines failed (exit code {code}); see {self.log}")
        r = json.loads(result.read_text())
        self.sfm, self.sfm_seconds = r.get("sfm"), float(r.get("sfm_seconds", 0.0))
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


def _demo_sift_conf() -> dict:
    """SIFT of the direct baseline for the demo: 4096 features at 1024 px (the bench uses 8192 at 1600)."""
    from services.matching import features as features_mod

    c = json.loads(json.dumps(features_mod.confs["sift"]))
    c["model"]["max_num_features"] = 4096
    c["preprocessing"]["resize_max"] = 1024
    c["output"] = "feats-sift-r1024-k4096"
    return c


def synthesize(out: Path, preset: str, seed: int, textures: Path | None, supersample: int, console) -> Path:
    """OUT/scene: the synthetic survey of `preset` (kept when complete)."""
    from services import synth

    scene = out / "scene"
    if not synth.scene_complete(scene):
        console.print(f"rendering the {preset} survey into {scene} (textures: {textures})")
        synth.main(
            synth.confs[preset],
            scene,
            seed=seed,
            textures_dir=textures,
            supersample=supersample,
            overwrite=True,
        )
    return scene


def _match_ground_pairs_ahead(job_dir: str, features: Path) -> bool:
    """In the child: the job's combined SfM's ground pairs matched into its pair cache from the child's
    copy of midview's features (the job's feature file, written by its stages, is not opened), so that
    the pipeline's combined SfM and the ALIKED+LightGlue baseline's read them. False if the features'
    conf is not the job's."""
    from services.pipeline import Job
    from services.pipeline.stages import match_ground_pairs_ahead

    job = Job.load(job_dir)
    if job.features_path.name != features.name:
        return False
    t0 = time.perf_counter()
    n = match_ground_pairs_ahead(job, features)
    logger.info("the combined SfM's %d ground pairs matched ahead in %.1f s", n, time.perf_counter() - t0)
    return True


def _run_pipeline(job, run_job: Callable, child, deadline: tuple[float, float] | None, console) -> dict:
    """The job's stages in three runs: those before the 3DGS (the aerial SfM); then, the child told that
    the aerial model is ready and the 3DGS's budget fitted to the deadline, those up to the matching;
    then, with the child's features, the rest. {stage: marker}."""
    todo = list(job.options.stages)
    cut = todo.index("match_views") if child is not None and "match_views" in todo else len(todo)
    first = todo.index("train_splat") if "train_splat" in todo[:cut] else 0
    results: dict = {}
    for i, stages in enumerate((todo[:first], todo[first:cut], todo[cut:])):
        if i == 1 and first and deadline:
            fit_splat_budget(job, time.perf_counter() - deadline[0], deadline[1], console)
        if i == 2 and stages and child.share_features(job.features_path):
            console.print("midview's features: taken from the baselines' process")
        if stages:
            results.update(run_job(job, stages=stages))
            if child is not None:
                child.aerial_model_ready()
    return results


def run_with_baselines(
    job,
    scene: Path,
    out: Path,
    baselines: bool,
    beside: bool,
    run_job: Callable,
    console,
    timings: dict,
    deadline: tuple[float, float] | None = None,
    baseline_sfm: bool = False,
) -> tuple[dict[str, tuple], dict[str, dict] | None]:
    """The pipeline, and the direct baselines beside it (a child process, which also extracts midview's
    features for the job and, with `baseline_sfm`, reconstructs with the baselines' matches once the
    aerial model is there) or after it. Returns {label: (match file, matching conf)} of the baselines
    and the child's reconstructions ({label: evaluate_sfm}; None when it made none).
    `deadline`: (the demo's start, perf_counter; its deadline in seconds): the 3DGS's budget is fitted to
    it once the stages before the 3DGS have run."""
    from services import pipeline
    from services.matching.views import feature_conf

    aliked = feature_conf(job.match_conf())
    sift = {"features": _demo_sift_conf()}
    child = None
    if baselines and beside:
        child = BaselinesBeside(scene, out / "baselines", aliked, sift, job.root if baseline_sfm else None)
        console.print(f"direct baselines beside the pipeline (log: {child.log})")
    found: dict[str, tuple] = {}
    try:
        t0 = time.perf_counter()
        results = _run_pipeline(job, run_job, child, deadline, console)
        timings["pipeline"] = time.perf_counter() - t0
        for s, r in results.items():
            timings[s] = float(r.get("seconds", 0.0))
        if baselines:
            t0 = time.perf_counter()
            with console.status("direct baselines"):
                if child is not None:
                    child.pipeline_done()
                    found, timings["baselines_process"] = child.wait()
                else:
                    pipeline.set_threads(job)
                    found = direct_baselines(scene, out / "baselines", aliked, sift, job.features_path)
            timings["baselines"] = time.perf_counter() - t0  # after the pipeline
    finally:
        if child is not None:  # done, or the pipeline failed: stop the child either way
            child.stop()
    if child is not None and child.sfm is not None:
        timings["baselines_sfm_beside"] = child.sfm_seconds
    return found, None if child is None else child.sfm


def reconstruct_baselines(job, found: dict[str, tuple], scene: Path, out: Path, console) -> dict[str, dict]:
    """Each baseline's combined reconstruction evaluated against the truth ({label: evaluate_sfm}); a
    baseline that cannot reconstruct has none."""
    from services.evaluation import evaluate_sfm

    sfm_evals = {}
    for label, (path, conf) in found.items():
        with console.status(f"reconstruction with the {label} matches"):
            try:
                model = baseline_reconstruction(job, label, path, conf, out / "baselines")
                sfm_evals[label] = evaluate_sfm(scene, model, out / "eval" / f"{path.stem}-combined")
            except Exception as e:  # noqa: BLE001 - a baseline that cannot reconstruct reports no NRI
                logger.warning("no reconstruction with the %s matches: %s", label, e)
    return sfm_evals


def run_demo(
    out: Path,
    preset: str,
    seed: int,
    textures: Path | None,
    renderer: str,
    options: dict,
    supersample: int,
    baselines: bool,
    baseline_sfm: bool,
    beside: bool,
    run_job: Callable,
    deadline_s: float | None = None,
) -> Path:
    """The demo (see the module docstring) with the job options `options`; returns OUT/report.html.
    `run_job(job, stages)` runs the pipeline's stages (with the command's progress display).
    `deadline_s`: seconds from the start by which the demo should end (the 3DGS's budget is fitted to it)."""
    from rich.console import Console

    from cli.demo_report import print_table, write_report_html
    from services import pipeline
    from services.evaluation import evaluate_matches, evaluate_sfm

    console = Console(width=None if sys.stdout.isatty() else 150)
    t_start = time.perf_counter()
    tex = textures or (DEFAULT_TEXTURES if DEFAULT_TEXTURES.is_dir() else None)
    timings: dict[str, float] = {}
    scene = synthesize(out, preset, seed, tex, supersample, console)
    timings["synth"] = time.perf_counter() - t_start
    settings = {
        "torch_threads": DEMO_TORCH_THREADS,
        "renderer": renderer,
        "scene": str(scene) if renderer == "gt" else None,
    }
    images = scene / "images"
    job = pipeline.Job.create(
        out / "job", images / "aerial", images / "ground", scene / "pos.csv", scene / "cameras.json",
        options=options, settings=settings,
    )  # fmt: skip
    deadline = (t_start, deadline_s) if deadline_s else None
    found, sfm_beside = run_with_baselines(
        job, scene, out, baselines, beside, run_job, console, timings, deadline, baseline_sfm
    )
    files: dict[str, Path] = {k: v[0] for k, v in found.items()}
    sfm_evals: dict[str, dict] = dict(sfm_beside or {})
    if baseline_sfm and found and sfm_beside is None:
        t0 = time.perf_counter()
        sfm_evals = reconstruct_baselines(job, found, scene, out, console)
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
    return report
