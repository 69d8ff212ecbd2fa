"""The `midview` command: help on every subcommand, clear errors with a non-zero exit."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
COMMANDS = [
    [],
    ["synth"],
    ["sfm"],
    ["eval"],
    ["eval", "matches"],
    ["eval", "sfm"],
    ["match"],
    ["match", "direct"],
    ["match", "export"],
    ["pos"],
    ["pos", "check"],
    ["splat"],
    ["splat", "train"],
    ["splat", "render"],
    ["run"],
    ["demo"],
    ["serve"],
    ["worker"],
]


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: " ".join(c) or "midview")
def test_help(cmd):
    result = runner.invoke(app, [*cmd, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output


def test_pos_check_reports_bad_rows(tmp_path):
    pos = tmp_path / "pos.csv"
    pos.write_text("name,lat,lon,h\naerial/a.jpg,55.7,13.2,abc\naerial/b.jpg,55.7,13.2,50\n")
    result = runner.invoke(app, ["pos", "check", str(pos)])
    assert result.exit_code == 2
    assert "line 2, column h: 'abc' is not a number" in result.output


def test_pos_check_against_images(tmp_path):
    (tmp_path / "images" / "aerial").mkdir(parents=True)
    (tmp_path / "images" / "aerial" / "a.jpg").write_bytes(b"x")
    (tmp_path / "images" / "aerial" / "c.jpg").write_bytes(b"x")
    pos = tmp_path / "pos.csv"
    pos.write_text("name,lat,lon,h\naerial/a.jpg,55.7,13.2,50\naerial/b.jpg,55.7,13.2,50\n")
    result = runner.invoke(app, ["pos", "check", str(pos), "--images", str(tmp_path / "images")])
    assert result.exit_code == 2
    assert "image 'aerial/c.jpg' has no POS row" in result.output
    assert "POS row 'aerial/b.jpg' names no uploaded image" in result.output
    pos.write_text("name,lat,lon,h\naerial/a.jpg,55.7,13.2,50\naerial/c.jpg,55.7,13.2,50\n")
    result = runner.invoke(app, ["pos", "check", str(pos), "--images", str(tmp_path / "images")])
    assert result.exit_code == 0, result.output
    assert "2 records" in result.output


def test_pos_check_reads_every_pos_format(tmp_path):
    from test_pos_formats import DJI_XMP, write_gps_jpeg

    from services.pos import PosRecord, write_pos_json, ypr_to_matrix

    flat = tmp_path / "flat"
    for n in ("DJI_1.JPG", "DJI_2.JPG"):
        write_gps_jpeg(flat / n, 55.7, 13.19, 80.0, xmp=DJI_XMP)
    result = runner.invoke(app, ["pos", "check", str(flat)])  # EXIF/XMP of an image folder
    assert result.exit_code == 0, result.output
    assert "image EXIF/XMP, CRS EPSG:4326, 2 records, 2 with attitude: OK" in result.output
    geo = tmp_path / "geo.txt"  # ODM: bare names, matched to the flat folder's aerial/ images
    geo.write_text("WGS84 UTM 33N\nDJI_1.JPG 500000 6170000 80 90 0 0\nDJI_2.JPG 500010 6170000 80\n")
    result = runner.invoke(app, ["pos", "check", str(geo), "--images", str(flat)])
    assert result.exit_code == 0, result.output
    assert "ODM geo.txt, CRS EPSG:32633, 2 records, 1 with attitude: OK" in result.output
    geo.write_text("EPSG:32633\nDJI_1.JPG 500000 nan 80\n")
    result = runner.invoke(app, ["pos", "check", str(geo), "--images", str(flat)])
    assert result.exit_code == 2 and "line 2, column y: 'nan' is not finite" in result.output
    recs = [PosRecord(f"aerial/DJI_{i}.JPG", 55.7, 13.19, 80.0, ypr_to_matrix(0, -90, 0)) for i in (1, 3)]
    js = write_pos_json(tmp_path / "pos.json", recs, crs="EPSG:25833")
    result = runner.invoke(app, ["pos", "check", str(js), "--images", str(flat)])
    assert result.exit_code == 2
    assert "image 'aerial/DJI_2.JPG' has no POS row" in result.output
    assert "POS row 'aerial/DJI_3.JPG' names no uploaded image" in result.output
    result = runner.invoke(app, ["pos", "check", str(js)])
    assert result.exit_code == 0 and "POS JSON, CRS EPSG:25833, 2 records" in result.output


def test_synth_rejects_unknown_preset(tmp_path):
    result = runner.invoke(app, ["synth", str(tmp_path / "s"), "--preset", "nope"])
    assert result.exit_code == 2
    assert "nope" in result.output


def test_run_of_a_stage_before_its_inputs_exist_says_which_stages_to_run(tiny_scene, tmp_path):
    """`midview run --stages splat_all` (or reduce) on a new job folder: a clear message naming the
    stages that make the missing inputs, exit code 2, nothing run."""
    s = tiny_scene
    args = [str(s / "images" / "aerial"), str(s / "images" / "ground"), str(s / "pos.csv")]
    out = tmp_path / "job"
    result = runner.invoke(
        app, ["run", *args, str(out), "--cameras", str(s / "cameras.json"), "--stages", "splat_all"]
    )
    assert result.exit_code == 2, result.output
    assert "splat_all needs combined/sparse (made by combined_sfm)" in result.output
    result = runner.invoke(
        app, ["run", *args, str(out), "--cameras", str(s / "cameras.json"), "--stages", "reduce"]
    )
    assert result.exit_code == 2
    for made_by in ("aerial_sfm", "render_views", "match_views"):
        assert f"(made by {made_by})" in result.output
    assert not (out / "stages" / "reduce.json").exists() and not (out / "transfer").exists()


def test_run_takes_splat_view_and_match_overrides_and_rejects_bad_ones(tiny_scene, tmp_path):
    """`midview run --splat-set/--view-set/--match-set/--render-set KEY=VALUE`: kept in job.json and used
    by the stages' confs; an unknown key or a value of the wrong kind exits 2 with the reason before a job
    folder is made."""
    from services.pipeline import Job

    s = tiny_scene
    args = [str(s / "images" / "aerial"), str(s / "images" / "ground"), str(s / "pos.csv")]
    cams = ["--cameras", str(s / "cameras.json")]
    bad = tmp_path / "bad"
    for item, msg in (
        (["--splat-set", "strategy.max_gausians=5"], "unknown key 'max_gausians'"),
        (["--splat-set", "strategy.max_gaussians=many"], "expected an integer"),
        (["--splat-set", "coarse_scale=2"], "coarse_scale must be in (0, 1]"),
        (["--view-set", "paper.height=0.4"], "unknown key 'height'"),
        (["--match-set", "render_keypoints=2048"], "unknown key 'render_keypoints'"),
        (["--match-set", "matcher.filter_threshold=low"], "expected a number"),
        (["--render-set", "colour=sharp"], "colour must be source or splat"),
        (["--render-set", "proxy.cells=2"], "unknown key 'cells'"),
    ):
        result = runner.invoke(app, ["run", *args, str(bad), *cams, *item])
        assert result.exit_code == 2, result.output
        assert msg in result.output
        assert not bad.exists()
    out = tmp_path / "job"
    sets = ["--splat-set", "strategy.max_gaussians=200000"]  # a conf entry wins over the option
    sets += ["--view-set", "paper.extra_height_fractions=[0.7]"]
    sets += ["--match-set", "render_detection_threshold=-1", "--match-set", "matcher.filter_threshold=0.05"]
    sets += ["--render-set", "colour=splat", "--render-set", "proxy.cell_m=2"]
    result = runner.invoke(app, ["run", *args, str(out), *cams, "--stages", "splat_all", *sets])
    assert result.exit_code == 2  # nothing before splat_all has run: the job is written, no stage run
    job = Job.load(out)
    assert job.splat_conf()["strategy"]["max_gaussians"] == 200000
    assert job.viewpoint_conf()["paper"]["extra_height_fractions"] == [0.7]
    mconf = job.match_conf()
    assert mconf["render_detection_threshold"] == -1 and mconf["matcher"]["filter_threshold"] == 0.05
    assert job.splat_conf()["max_width"] == 400
    assert job.render_conf()["colour"] == "splat" and job.render_conf()["proxy"]["cell_m"] == 2.0


def test_demo_rejects_a_negative_time_budget(tmp_path):
    result = runner.invoke(app, ["demo", str(tmp_path / "demo"), "--splat-time-budget", "-5"])
    assert result.exit_code == 2
    assert "--splat-time-budget-s: Input should be greater than or equal to 1" in result.output
    assert not (tmp_path / "demo").exists()


def test_run_and_demo_take_every_job_option_from_the_model(tiny_scene, tmp_path):
    """A flag per JobOptions field with each profile's default in its help; a flag not given leaves the
    option to --profile (cpu by default), a flag given wins."""
    from services.pipeline import JobOptions

    for command in ("run", "demo"):
        text = runner.invoke(app, [command, "--help"], env={"COLUMNS": "400"}).output
        for name in set(JobOptions.model_fields) - {"stages"} - ({"seed"} if command == "demo" else set()):
            assert "--" + name.replace("_", "-") in text, (command, name)
        # the same defaults per profile as GET /options (option_specs): one declaration
        from services.pipeline import option_specs

        flat = " ".join(text.split())
        for spec in option_specs():
            values = set(map(str, spec["defaults"].values()))
            if spec["name"] in ("stages", "profile") or len(values) == 1:
                continue
            shown = ", ".join(f"{p} {v}" for p, v in spec["defaults"].items())
            assert f"defaults {shown}" in flat, (command, spec["name"], shown)
    images = tiny_scene / "images"
    base = ["run", str(images / "aerial"), str(images / "ground"), str(tiny_scene / "pos.csv")]
    for profile, extra in (
        ("cpu", []),
        ("gpu", ["--profile", "gpu"]),
        ("mixed", ["--profile", "gpu", "--splat-steps", "123"]),
    ):
        out = tmp_path / profile
        r = runner.invoke(app, [*base, str(out), "--stages", "nope", *extra])  # stops before any stage runs
        assert r.exit_code == 2 and "unknown stage" in r.output
        r = runner.invoke(
            app, [*base, str(out), "--from", "combined_sfm", "--stages", "combined_sfm", *extra]
        )
        options = json.loads((out / "job.json").read_text())["options"]
        expected = {"cpu": (3000, 400), "gpu": (7000, 1600), "mixed": (123, 1600)}[profile]
        assert (options["splat_steps"], options["splat_max_width"]) == expected, (profile, r.output)


def test_demo_exits_with_the_reason_when_a_stage_cannot_go_on(tiny_scene, tmp_path, monkeypatch):
    """A stage that cannot go on with its inputs (pipeline.StageError, e.g. a plan without views) ends
    the demo with its reason and exit status 2, not a traceback."""
    import cli.run
    from services import pipeline

    def plan_fails(job, stages=None, from_stage=None, force=False):
        raise pipeline.StageError("no intermediate view could be planned (planner paper, ...)")

    monkeypatch.setattr(cli.run, "run_job", plan_fails)
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "scene").symlink_to(tiny_scene)  # a complete scene: not synthesised again
    result = runner.invoke(app, ["demo", str(tmp_path / "demo"), "--preset", "tiny", "--no-baselines"])
    assert result.exit_code == 2, result.output
    assert "no intermediate view could be planned" in result.output and "Traceback" not in result.output


def test_run_rejects_a_time_budget_under_a_second(tmp_path):
    """The job option splat_time_budget_s (API and CLI): at least 1 s; nothing is created otherwise."""
    args = [str(tmp_path / d) for d in ("aerial", "ground", "pos.csv", "job")]
    for d in ("aerial", "ground"):
        (tmp_path / d).mkdir()
    (tmp_path / "pos.csv").write_text("name,lat,lon,h\n")
    result = runner.invoke(app, ["run", *args, "--splat-time-budget", "0.5"])
    assert result.exit_code == 2
    assert "--splat-time-budget-s: Input should be greater than or equal to 1" in result.output
    assert not (tmp_path / "job").exists()
