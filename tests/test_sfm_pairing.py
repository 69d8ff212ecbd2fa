"""Aerial SfM pairs from the POS: footprints of constructed nadir and oblique cameras, their overlap,
the pairing modes, and a footprint-paired reconstruction of the tiny synthetic scene."""

from __future__ import annotations

import json

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cli.sfm import sfm as sfm_command
from services.colmap_model import Camera
from services.pos import LocalFrame, PosRecord, ypr_to_matrix
from services.sfm import pairing

CAM = Camera("PINHOLE", 200, 100, [100.0, 100.0, 100.0, 50.0])  # 90 x 53 degrees
FRAME = LocalFrame(55.70, 13.19, 100.0)


def _extent(poly: np.ndarray) -> np.ndarray:
    return np.r_[poly.min(0), poly.max(0)]


# -- polygons and footprints -------------------------------------------------------------------
def test_convex_clipping_and_overlap():
    sq = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    assert pairing.polygon_area(sq) == 4.0 and pairing.polygon_area(sq[::-1]) == -4.0
    assert abs(pairing.polygon_area(pairing.intersect_convex(sq, sq + [1.0, 1.0]))) == pytest.approx(1.0)
    tri = np.array([[1.0, -1.0], [3.0, 1.0], [1.0, 3.0]])  # clockwise or not, the same intersection
    a = abs(pairing.polygon_area(pairing.intersect_convex(sq, tri)))
    assert a == pytest.approx(abs(pairing.polygon_area(pairing.intersect_convex(sq, tri[::-1]))))
    assert a == pytest.approx(2.0)  # the triangle covers x >= 1 of the square
    assert pairing.overlap(sq, sq + [1.0, 0.0]) == pytest.approx(0.5)
    assert pairing.overlap(sq, sq + [5.0, 0.0]) == 0.0
    assert pairing.overlap(sq, 0.5 * sq) == pytest.approx(1.0)  # inside: all of the smaller one


def test_footprint_of_a_nadir_camera():
    fp = pairing.footprint_polygon(np.array([10.0, 20.0, 100.0]), ypr_to_matrix(0, -90, 0), CAM, 0.0)
    np.testing.assert_allclose(_extent(fp), [10 - 100, 20 - 50, 10 + 100, 20 + 50], atol=1e-9)
    assert pairing.polygon_area(fp) == pytest.approx(200 * 100)  # counter-clockwise
    turned = pairing.footprint_polygon(np.array([0.0, 0.0, 100.0]), ypr_to_matrix(90, -90, 0), CAM, 0.0)
    np.testing.assert_allclose(_extent(turned), [-50, -100, 50, 100], atol=1e-9)  # image top east
    assert (
        pairing.footprint_polygon(np.array([0.0, 0.0, 100.0]), ypr_to_matrix(0, -90, 0), CAM, 120.0) is None
    )


def test_footprints_of_oblique_cameras():
    c = np.array([0.0, 0.0, 100.0])
    half = np.degrees(np.arctan(0.5))  # half the vertical field of view
    near = 100 / np.tan(np.radians(45 + half))
    fp = pairing.footprint_polygon(c, ypr_to_matrix(0, -45, 0), CAM, 0.0)
    ext = _extent(fp)  # looking north: a trapezoid from `near` to 300 m ahead
    assert ext[1] == pytest.approx(near) and ext[3] == pytest.approx(100 / np.tan(np.radians(45 - half)))
    assert ext[2] - ext[0] > 200  # wider far away
    cut = pairing.footprint_polygon(c, ypr_to_matrix(0, -45, 0), CAM, 0.0, max_range_factor=2.0)
    assert _extent(cut)[3] == pytest.approx(200.0) and _extent(cut)[1] == pytest.approx(near)
    horizon = pairing.footprint_polygon(c, ypr_to_matrix(90, 0, 0), CAM, 0.0)  # half the image is sky
    np.testing.assert_allclose(_extent(horizon)[[0, 2]], [100 / np.tan(np.radians(half)), 500.0])
    assert pairing.footprint_polygon(c, ypr_to_matrix(0, 30, 0), CAM, 0.0) is None  # all sky


# -- pairs -------------------------------------------------------------------------------------
def _record(name: str, enu, ypr=None, rel_alt=None) -> PosRecord:
    lat, lon, h = (float(v[0]) for v in FRAME.to_wgs84(np.array([enu], float)))
    R = None
    if ypr is not None:  # attitudes are given in the frame's ENU: into the ENU at the camera
        R = FRAME.rotation_to_enu_at(lat, lon) @ ypr_to_matrix(*ypr)
    return PosRecord(name, lat, lon, h, R, rel_alt=rel_alt)


def _survey() -> dict[str, PosRecord]:
    """A and B: overlapping nadirs; C: a nadir far east; D: an oblique south of A looking north over A
    and B; E: an oblique at C looking south, away from C's footprint; F: no attitude, next to C."""
    recs = [
        _record("aerial/A.jpg", [0, 0, 100], (0, -90, 0)),
        _record("aerial/B.jpg", [100, 0, 100], (0, -90, 0)),
        _record("aerial/C.jpg", [1000, 0, 100], (0, -90, 0)),
        _record("aerial/D.jpg", [0, -150, 100], (0, -45, 0)),
        _record("aerial/E.jpg", [1000, 0, 100], (180, -30, 0)),
        _record("aerial/F.jpg", [1010, 0, 100]),
    ]
    return {r.name: r for r in recs}


def test_footprint_pairs_of_constructed_cameras():
    recs = _survey()
    names = sorted(recs)
    conf = {"pairs": "footprint", "num_neighbors": 2, "footprint": {"height_above_ground": 100.0}}
    mode, pairs = pairing.get_pairs(conf, names, recs, FRAME, {n: CAM for n in names})
    short = {tuple(n[7] for n in p) for p in pairs}
    assert mode == "footprint"
    # nadir-nadir overlapping, oblique over both nadirs; C and E share a station but not the ground;
    # F (no attitude) gets its spatial neighbours instead
    assert short == {("A", "B"), ("A", "D"), ("B", "D"), ("C", "F"), ("E", "F")}
    polys = pairing.footprints(names, recs, FRAME, {n: CAM for n in names}, 0.0)
    assert polys["aerial/F.jpg"] is None
    assert pairing.overlap(polys["aerial/A.jpg"], polys["aerial/B.jpg"]) == pytest.approx(0.5, abs=1e-3)
    assert pairing.overlap(polys["aerial/C.jpg"], polys["aerial/E.jpg"]) == 0.0
    # the oblique's footprint holds all of A and 88% of B: a 0.9 threshold keeps only A-D
    _, strict = pairing.get_pairs(
        {**conf, "footprint": {**conf["footprint"], "min_overlap": 0.9}},
        names,
        recs,
        FRAME,
        {n: CAM for n in names},
    )
    assert {tuple(n[7] for n in p) for p in strict} == {("A", "D"), ("C", "F"), ("E", "F")}


def test_pairing_modes_and_terrain_height():
    recs = _survey()
    names = sorted(recs)
    cams = {n: CAM for n in names}
    all_pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
    assert pairing.get_pairs({}, names, recs, FRAME, cams) == ("exhaustive", all_pairs)
    big = {"exhaustive_max": 2, "num_neighbors": 2}
    assert pairing.get_pairs(big, names, recs, FRAME, cams)[0] == "spatial"  # attitudes 5/6 < 0.9
    with_att = {n: r for n, r in recs.items() if r.R_world_from_cam is not None}
    n5 = sorted(with_att)
    assert pairing.get_pairs(big, n5, with_att, FRAME, cams)[0] == "spatial"  # no terrain height
    ground = {**big, "footprint": {"ground_h": 0.0}}
    assert pairing.get_pairs(ground, n5, with_att, FRAME, cams)[0] == "footprint"
    # DJI relative altitude: the terrain is the take-off height (h - rel_alt), 90 m below the cameras
    dji = {n: PosRecord(n, r.lat, r.lon, r.h, r.R_world_from_cam, rel_alt=90.0) for n, r in with_att.items()}
    z, source = pairing.terrain_z(dji, FRAME, pairing.default_conf)
    assert z == pytest.approx(10.0, abs=0.01) and source == "POS relative altitude"
    assert pairing.get_pairs(big, n5, dji, FRAME, cams)[0] == "footprint"
    z, _ = pairing.terrain_z(with_att, FRAME, {"footprint": {"ground_h": 100.0 - 30.0}})
    assert z == pytest.approx(-30.0, abs=0.01)
    with pytest.raises(ValueError, match="unknown pairing 'nope'"):
        pairing.get_pairs({"pairs": "nope"}, n5, with_att, FRAME, cams)
    with pytest.raises(ValueError, match="no terrain height"):
        pairing.get_pairs({"pairs": "footprint"}, n5, with_att, FRAME, cams)


# -- end to end --------------------------------------------------------------------------------
def test_footprint_pairs_on_the_tiny_scene(tiny_scene, tmp_path):
    """A 2 x 2 grid of stations of a nadir and four obliques, 40 m up: footprint pairs leave out the
    obliques that look away from each other, and every image still registers."""
    app = typer.Typer()
    app.command("sfm")(sfm_command)
    app.command("other")(lambda: None)
    out = tmp_path / "sfm"
    args = ["sfm", str(tiny_scene), str(out), "--pairs", "footprint", "--height-above-ground", "40"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    pairs = {tuple(sorted(ln.split())) for ln in (out / "pairs.txt").read_text().splitlines()}
    assert 5 < len(pairs) < 190 // 2
    nadirs = ["aerial/A0001.jpg", "aerial/A0006.jpg", "aerial/A0011.jpg", "aerial/A0016.jpg"]
    assert all((a, b) in pairs for i, a in enumerate(nadirs) for b in nadirs[i + 1 :])
    assert ("aerial/A0002.jpg", "aerial/A0004.jpg") not in pairs  # north and south obliques of a station
    report = json.loads((out / "report.json").read_text())
    assert report["pairing"] == f"footprint ({len(pairs)} pairs)"
    assert report["num_registered"] == 20 and report["georef"]["residual_m"]["max"] < 2.0
