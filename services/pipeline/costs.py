"""How long a job takes: a cost model per stage, fitted on the timed runs of `bench/pipeline_time.py`
(docs/results/pipeline-time.json, every default stage of `midview run` alone on a 2-core machine).

Each stage costs `seconds_per_unit x units`, its units counted from the survey and the options: the
aerial SfM per aerial image and 4096 SIFT features (twice the features: about twice the matching and
points; measured 2.06x on `isprs`), the 3DGS per training step of at most 60k Gaussians (a larger cap: its
0.6th power; at most splat_epochs passes over the aerial images it trains on, every 8th held out; at most
its time budget), the views' planning,
rendering, matching and reduction per planned view (ground images x views per ground image x planners),
the combined reconstruction per ground image. FIT holds the fitted seconds per unit with the fit's
leave-one-out relative error (`bench/pipeline_time.py --fit` prints it; tests/test_costs.py checks it
against the results file). Measured for the `cpu` profile only: no GPU machine timed the `gpu` profile,
so its estimate is None.
"""

from __future__ import annotations

import math
from typing import Any

from services.pipeline.options import JobOptions

# seconds per unit of each stage on 2 CPU cores (cpu profile) and the fit's leave-one-out relative error
# (median, max over the runs): bench/pipeline_time.py --fit on docs/results/pipeline-time.json
FIT: dict[str, Any] = {
    "seconds_per_unit": {
        "aerial_sfm": 1.5797,
        "train_splat": 0.0991,
        "plan_views": 0.3585,
        "render_views": 1.6147,
        "match_views": 6.2328,
        "reduce": 0.3775,
        "combined_sfm": 1.7117,
    },
    "relative_error": {"median": 0.355, "max": 0.624},
    "runs": 4,
}
PROFILES_MEASURED = ("cpu",)


def units(options: JobOptions, n_aerial: int, n_ground: int) -> dict[str, float]:
    """The units of each default stage of a job on a survey of n_aerial and n_ground images."""
    planners = 2 if options.view_planner == "both" else 1
    views = float(n_ground * options.views_per_ground_image * planners)
    # a step's cost grows with the Gaussians' cap as its 0.6th power (3000 steps on `isprs`: 295 s with
    # 60k, 448 s with 120k, 1.52x); no cap counted as a million
    gaussians = (options.splat_max_gaussians or 1_000_000) / 60_000.0
    steps = float(options.splat_steps)
    if options.splat_epochs is not None:  # every 8th aerial image held out (services.splat's test_every)
        steps = min(steps, round(options.splat_epochs * (n_aerial - math.ceil(n_aerial / 8))))
    return {
        "aerial_sfm": n_aerial * options.sfm_max_features / 4096.0,
        "train_splat": steps * gaussians**0.6,
        "plan_views": views,
        "train_blocks": 0.0 if options.block_steps == 0 else float(options.block_steps),
        "render_views": views,
        "match_views": views,
        "reduce": views,
        "combined_sfm": float(n_ground),
    }


def estimate(
    options: JobOptions, n_aerial: int, n_ground: int, fit: dict[str, Any] | None = None
) -> dict[str, Any]:
    """{"stages_s": {stage: seconds or None}, "total_s": seconds or None, "relative_error": {median, max}}
    for the job's stages; None where the model has no measurement (another profile, a stage not fitted)."""
    fit = fit or FIT
    per_unit = fit["seconds_per_unit"] if options.profile in PROFILES_MEASURED else {}
    stages: dict[str, float | None] = {}
    for stage, n in units(options, n_aerial, n_ground).items():
        if stage not in options.stages:
            continue
        if n == 0:
            stages[stage] = 0.0
        elif stage in per_unit:
            seconds = per_unit[stage] * n
            if stage == "train_splat" and options.splat_time_budget_s is not None:
                seconds = min(seconds, float(options.splat_time_budget_s))
            stages[stage] = round(seconds, 1)
        else:
            stages[stage] = None
    known = [s for s in stages.values() if s is not None]
    total = round(sum(known), 1) if known and len(known) == len(stages) else None
    return {"stages_s": stages, "total_s": total, "relative_error": dict(fit["relative_error"])}


# what a run recorded before these options existed ran with: no epoch cap, the SIFT SfM at 1600 px with
# 8192 features and 20 neighbours, the CPU 3DGS preset's 60k Gaussians
BEFORE_OPTIONS: dict[str, Any] = {
    "splat_epochs": None,
    "sfm_max_image_size": 1600,
    "sfm_max_features": 8192,
    "sfm_neighbors": 20,
    "splat_max_gaussians": 60_000,
}


def run_options(run: dict[str, Any]) -> JobOptions:
    """The options a timed run ran with (those it does not record: BEFORE_OPTIONS)."""
    return JobOptions.model_validate({**BEFORE_OPTIONS, **run["options"]})


def fit_runs(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """FIT from timed runs ({"survey": {aerial, ground}, "options": JobOptions fields, "stages_s"}): per
    stage the least-squares seconds per unit through the origin; the error of predicting each run's
    total from the others (leave-one-out)."""

    def per_unit(rs: list[dict[str, Any]]) -> dict[str, float]:
        out = {}
        for stage in units(JobOptions(), 1, 1):
            pairs = []
            for r in rs:
                opts = run_options(r)
                n = units(opts, r["survey"]["aerial"], r["survey"]["ground"])[stage]
                s = r["stages_s"].get(stage)
                budget = opts.splat_time_budget_s
                if s is None or n == 0 or (stage == "train_splat" and budget and s >= 0.95 * budget):
                    continue  # a 3DGS stopped by its budget says nothing of its pace
                pairs.append((n, float(s)))
            if pairs:
                out[stage] = round(sum(n * s for n, s in pairs) / sum(n * n for n, _ in pairs), 4)
        return out

    errors = []
    for i, r in enumerate(runs):
        rest = runs[:i] + runs[i + 1 :]
        if not rest:
            continue
        opts = run_options(r)
        pred = estimate(opts, r["survey"]["aerial"], r["survey"]["ground"],
                        {"seconds_per_unit": per_unit(rest), "relative_error": {}})  # fmt: skip
        if pred["total_s"]:
            errors.append(abs(pred["total_s"] / sum(r["stages_s"].values()) - 1.0))
    errors.sort()
    return {
        "seconds_per_unit": per_unit(runs),
        "relative_error": {
            "median": round(errors[len(errors) // 2], 3) if errors else None,
            "max": round(errors[-1], 3) if errors else None,
        },
        "runs": len(runs),
    }
