"""`midview demo --deadline`: the 3DGS trains for what the stages before it leave of the deadline, within
the floor and the --splat-time-budget cap; the job keeps the budget, a trained 3DGS keeps its own."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from cli.demo import DEMO_AFTER_SPLAT_RATIO, DEMO_SPLAT_MIN_S, fit_splat_budget, splat_budget_for_deadline
from cli.main import app
from services.pipeline import Job

runner = CliRunner()


def test_the_budget_is_what_the_deadline_leaves_within_floor_and_cap():
    # a fast machine: the stages before the 3DGS took 3.3 min; the cap decides
    assert splat_budget_for_deadline(200.0, 1140.0, 540.0) == 540.0
    # a slow one: 4.4 min before; the stages after are estimated at 1.8 times that
    assert splat_budget_for_deadline(264.0, 1140.0, 540.0) == pytest.approx(1140.0 - 264.0 * 2.8)
    # far too slow: the floor, not a 3DGS of a handful of steps
    assert splat_budget_for_deadline(900.0, 1140.0, 540.0) == DEMO_SPLAT_MIN_S
    # no cap (--splat-time-budget 0): the deadline alone
    assert splat_budget_for_deadline(100.0, 1140.0, None) == pytest.approx(1140.0 - 100.0 * 2.8)
    assert DEMO_AFTER_SPLAT_RATIO == pytest.approx(1.8)


class _Console:
    def __init__(self):
        self.lines = []

    def print(self, line):
        self.lines.append(line)


def _job(tiny_scene, root, budget):
    images = tiny_scene / "images"
    return Job.create(
        root, images / "aerial", images / "ground", tiny_scene / "pos.csv", tiny_scene / "cameras.json",
        options={"splat_time_budget_s": budget},
    )  # fmt: skip


def test_the_job_keeps_the_fitted_budget_and_a_trained_3dgs_keeps_its_own(tiny_scene, tmp_path):
    job = _job(tiny_scene, tmp_path / "job", 540.0)
    console = _Console()
    assert fit_splat_budget(job, 264.0, 1140.0, console) == pytest.approx(400.8)
    assert Job.load(tmp_path / "job").options.splat_time_budget_s == pytest.approx(400.8)
    assert job.splat_conf()["time_budget_s"] == pytest.approx(400.8)
    assert "3DGS time budget: 401 s" in console.lines[0]
    # a rerun of the demo in the same folder: the 3DGS trained (or killed while training) with 400.8 s
    # keeps its budget, so that it is neither trained again nor restarted
    job.splat.dir.mkdir(parents=True, exist_ok=True)
    (job.splat / "conf.json").write_text(json.dumps({**job.splat_conf(), "time_budget_s": 400.8}))
    again = _job(tiny_scene, tmp_path / "job", 540.0)
    assert fit_splat_budget(again, 10.0, 1140.0, console) == pytest.approx(400.8)
    assert Job.load(tmp_path / "job").options.splat_time_budget_s == pytest.approx(400.8)


@pytest.mark.parametrize(("deadline", "budget"), [("0.05", DEMO_SPLAT_MIN_S), ("19", 300.0)])
def test_the_demo_fits_the_budget_before_the_3dgs_trains(tiny_scene, tmp_path, monkeypatch, deadline, budget):
    """The demo runs the stages before train_splat, fits the budget, then runs train_splat with it."""
    import cli.run
    from services import pipeline

    calls = []

    def record(job, stages=None, from_stage=None, force=False):
        calls.append((list(stages), job.options.splat_time_budget_s))
        if "train_splat" in stages:
            raise pipeline.StageError("stopped here by the test")
        return {}

    monkeypatch.setattr(cli.run, "run_job", record)
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "scene").symlink_to(tiny_scene)
    args = ["demo", str(tmp_path / "demo"), "--preset", "tiny", "--no-baselines", "--deadline", deadline]
    result = runner.invoke(app, args)
    assert result.exit_code == 2 and "stopped here by the test" in result.output, result.output
    (before, _), (rest, fitted) = calls
    assert before == ["aerial_sfm"] and rest[0] == "train_splat"
    assert fitted == pytest.approx(budget)
    assert "3DGS time budget" in result.output


def test_the_demo_rejects_a_negative_deadline(tmp_path):
    result = runner.invoke(app, ["demo", str(tmp_path / "demo"), "--deadline", "-1"])
    assert result.exit_code == 2 and "--deadline must be >= 0 minutes" in result.output
    assert not (tmp_path / "demo").exists()
