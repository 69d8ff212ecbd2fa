"""The `midview` command: help on every subcommand, clear errors with a non-zero exit."""

from __future__ import annotations

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


def test_synth_rejects_unknown_preset(tmp_path):
    result = runner.invoke(app, ["synth", str(tmp_path / "s"), "--preset", "nope"])
    assert result.exit_code == 2
    assert "nope" in result.output
