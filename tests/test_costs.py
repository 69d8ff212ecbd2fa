"""The cost model of a job's time (services.pipeline.costs): fitted on bench/pipeline_time.py's runs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.pipeline import JobOptions, costs

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "pipeline-time.json"


def test_the_model_is_the_fit_of_the_timed_runs():
    """FIT is what `bench/pipeline_time.py --fit` computes from docs/results/pipeline-time.json."""
    doc = json.loads(RESULTS.read_text())
    assert costs.FIT == doc["fit"] == costs.fit_runs(doc["runs"])
    assert {"isprs", "tiny"} <= {r["preset"] for r in doc["runs"]}


def test_estimates_grow_with_the_survey_and_the_3dgs_keeps_its_budget():
    cpu = JobOptions()
    small, large = costs.estimate(cpu, 20, 10), costs.estimate(cpu, 200, 100)
    assert 0 < small["total_s"] < large["total_s"]
    assert large["stages_s"]["train_splat"] <= cpu.splat_time_budget_s
    assert set(small["stages_s"]) == set(cpu.stages)
    # two planners render twice the views
    both = JobOptions(view_planner="both")
    twice = costs.estimate(both, 20, 10)["stages_s"]["render_views"]
    assert abs(twice - 2 * small["stages_s"]["render_views"]) <= 0.2  # rounded to 0.1 s
    # the gpu profile was never timed: no figure
    assert costs.estimate(JobOptions.model_validate({"profile": "gpu"}), 20, 10)["total_s"] is None


def test_the_3dgs_of_a_small_survey_is_counted_in_passes_over_its_images():
    """The cpu profile's 3DGS trains at most splat_epochs passes over the aerial images it trains on
    (every 8th held out): a 20-image survey 60 x 17 steps, isprs's 60 images the whole splat_steps; a
    step of 120k Gaussians at most costs 2 ** 0.6 that of 60k, of no cap more."""
    cpu = JobOptions()
    assert cpu.splat_epochs == 60 and cpu.splat_max_gaussians == 120_000
    per_step = 2.0**0.6
    assert costs.units(cpu, 20, 4)["train_splat"] == pytest.approx(60 * 17 * per_step)
    assert costs.units(cpu, 60, 20)["train_splat"] == pytest.approx(cpu.splat_steps * per_step)
    small = JobOptions(splat_epochs=None, splat_max_gaussians=60_000)
    assert costs.units(small, 20, 4)["train_splat"] == 3000
    assert costs.units(JobOptions(splat_max_gaussians=0), 60, 20)["train_splat"] > 3000 * per_step


def test_the_fit_of_runs_recovers_their_rates():
    """Runs made from known seconds per unit give those rates back, and a leave-one-out error of 0."""
    rates = {"aerial_sfm": 3.0, "train_splat": 0.1, "plan_views": 1.0, "render_views": 2.0,
             "match_views": 4.0, "reduce": 0.5, "combined_sfm": 2.0}  # fmt: skip
    runs = []
    for aerial, ground in ((10, 4), (60, 20), (40, 40)):
        options = JobOptions(splat_time_budget_s=None).model_dump(mode="json")
        units = costs.units(JobOptions.model_validate(options), aerial, ground)
        stages = {s: rates.get(s, 0.0) * n for s, n in units.items()}
        runs.append({"survey": {"aerial": aerial, "ground": ground}, "options": options, "stages_s": stages})
    fit = costs.fit_runs(runs)
    assert fit["seconds_per_unit"] == rates and fit["relative_error"] == {"median": 0.0, "max": 0.0}
