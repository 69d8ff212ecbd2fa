"""The ALIKED path of the aerial SfM: in-plane turns from the POS, the POS check of verified pairs, the
georeference status, and ALIKED + LightGlue on the tiny synthetic scene."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
import typer
from typer.testing import CliRunner

from cli.sfm import sfm as sfm_command
from services.pos import LocalFrame, PosRecord, read_pos_csv, write_pos_csv, ypr_to_matrix
from services.sfm import GeorefError, confs, main, pairing, verify
from services.sfm.aerial import unrotate_keypoints
from services.sfm.georef import Georef, status

FRAME = LocalFrame(55.70, 13.19, 100.0)


def _app() -> typer.Typer:
    app = typer.Typer()
    app.command("sfm")(sfm_command)
    app.command("other")(lambda: None)
    return app


# -- in-plane turns ----------------------------------------------------------------------------
@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_keypoints_of_a_turned_image_map_back(k):
    w, h = 7, 4
    img = np.zeros((h, w), np.uint8)
    img[1, 5] = 255  # row 1, column 5: pixel centre (5.5, 1.5) in COLMAP pixels
    turned = np.rot90(img, k)
    r, c = np.argwhere(turned == 255)[0]
    back = unrotate_keypoints(np.array([[c + 0.5, r + 0.5]]), k, w, h)
    np.testing.assert_allclose(back, [[5.5, 1.5]])


def test_quarter_turns_from_attitudes():
    nadir_n, nadir_s = ypr_to_matrix(0, -90, 0), ypr_to_matrix(180, -90, 0)  # serpentine flight lines
    assert pairing.quarter_turns(nadir_n, nadir_n) == 0
    assert pairing.quarter_turns(nadir_n, nadir_s) == 2
    east, west = ypr_to_matrix(90, -45, 0), ypr_to_matrix(270, -45, 0)
    assert pairing.quarter_turns(nadir_n, east) == 1  # np.rot90(nadir, 1) looks like the east oblique
    assert pairing.quarter_turns(nadir_n, west) == 3
    assert pairing.quarter_turns(east, ypr_to_matrix(90, -40, 5)) == 0
    recs = {
        "a": PosRecord("a", 0, 0, 0, nadir_n),
        "b": PosRecord("b", 0, 0, 0, nadir_s),
        "c": PosRecord("c", 0, 0, 0, east),
        "d": PosRecord("d", 0, 0, 0, None),
        "e": PosRecord("e", 0, 0, 0, ypr_to_matrix(95, -88, 0)),  # nadir, image top east
    }
    # north up: the south-bound nadir turns half round, the east oblique and nadir a quarter clockwise
    assert pairing.upright_turns(recs, list(recs)) == {"a": 0, "b": 2, "c": 3, "d": 0, "e": 3}


# -- POS check of verified pairs ---------------------------------------------------------------
def _pair_database(path, R2, c2, wrong: bool, shift: float = 120.0):
    """Two images of random ground points seen from the POS poses (nadir at 0, 0, 50 and R2, c2); with
    `wrong` the second image's matches are shifted by `shift` px across the baseline (a repeated-pattern
    mismatch; along it, it would look like a different depth, which no POS check can tell)."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-20, 20, (80, 2)), rng.uniform(0, 8, 80)]
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240])
    poses = [(ypr_to_matrix(0, -90, 0), np.array([0.0, 0.0, 50.0])), (R2, c2)]
    kps = []
    for R, c in poses:
        Xc = (X - c) @ R  # camera frame: R_world_from_cam^T (X - c)
        kps.append(Xc[:, :2] / Xc[:, 2:] * 500 + [320, 240])
    if wrong:
        kps[1] = kps[1] + [0.0, shift]
    db = pycolmap.Database.open(str(path))
    cam_id = db.write_camera(cam)
    ids = []
    for n, kp in zip(("aerial/1.jpg", "aerial/2.jpg"), kps, strict=True):
        iid = db.write_image(pycolmap.Image(name=n, camera_id=cam_id))
        db.write_keypoints(iid, kp.astype(np.float32))
        ids.append(iid)
    tvg = pycolmap.TwoViewGeometry()
    tvg.config = 2
    tvg.inlier_matches = np.c_[np.arange(80), np.arange(80)].astype(np.uint32)
    db.write_two_view_geometry(ids[0], ids[1], tvg)
    db.close()
    recs = {}
    for n, (R, c) in zip(("aerial/1.jpg", "aerial/2.jpg"), poses, strict=True):
        lat, lon, h = (float(v[0]) for v in FRAME.to_wgs84(c[None]))
        recs[n] = PosRecord(n, lat, lon, h, FRAME.rotation_to_enu_at(lat, lon) @ R, 0.3, 0.5)
    return recs


@pytest.mark.parametrize(
    ("R2", "c2", "kind", "shift"),
    [
        (ypr_to_matrix(0, -90, 0), np.array([15.0, 0.0, 50.0]), "long", 120.0),  # along a flight line
        # an oblique of the station: wrong matches 30 degrees off (the tiny scene's were 45-50)
        (ypr_to_matrix(90, -60, 0), np.array([0.0, 0.3, 50.2]), "short", 290.0),
    ],
)
def test_pos_check_keeps_true_pairs_and_removes_wrong_ones(tmp_path, R2, c2, kind, shift):
    long_ref = None
    if kind == "short":  # the scene depth comes from a long-baseline pair
        long_ref = tmp_path / "ref.db"
    for wrong in (False, True):
        path = tmp_path / f"{wrong}.db"
        recs = _pair_database(path, R2, c2, wrong, shift)
        if long_ref is not None:  # add a long-baseline pair of the same scene as images 3 and 4
            recs_l = _pair_database(long_ref, ypr_to_matrix(0, -90, 0), np.array([15.0, 0.0, 50.0]), False)
            db = pycolmap.Database.open(str(path))
            ldb = pycolmap.Database.open(str(long_ref))
            ids = []
            for im in ldb.read_all_images():
                new = db.write_image(pycolmap.Image(name=im.name.replace("aerial/", "aerial/l"), camera_id=1))
                db.write_keypoints(new, ldb.read_keypoints(im.image_id))
                ids.append(new)
            tvg = ldb.read_two_view_geometry(1, 2)
            db.write_two_view_geometry(ids[0], ids[1], tvg)
            ldb.close()
            db.close()
            long_ref.unlink()
            recs.update({n.replace("aerial/", "aerial/l"): r for n, r in recs_l.items()})
        out = verify.check_pairs(path, recs, FRAME)
        removed = {tuple(r["pair"]) for r in out["rejected"]}
        assert (("aerial/1.jpg", "aerial/2.jpg") in removed) == wrong, out
        assert not any("aerial/l" in p[0] for p in removed)
        db = pycolmap.Database.open(str(path))
        assert db.exists_two_view_geometry(1, 2) != wrong
        db.close()
        if not wrong:  # triangulated from the (true) long-baseline pair: 50 m up, points 0-8 m high
            assert out["depth_m"] == pytest.approx(46.0, abs=4.0)


def test_pos_check_functions_on_exact_rays():
    rng = np.random.default_rng(1)
    X1 = np.c_[rng.uniform(-5, 5, (50, 2)), rng.uniform(20, 40, 50)]
    R, t = ypr_to_matrix(10, -80, 3).T @ ypr_to_matrix(15, -85, 0), np.array([4.0, -1.0, 0.5])
    X2 = X1 @ R.T + t
    x1, x2 = verify._unit(X1), verify._unit(X2)
    assert np.max(verify.epipolar_errors_deg(x1, x2, R, t)) < 1e-6
    found, mask = verify.fit_translation(x1, x2, R, 1.0)
    tn = t / np.linalg.norm(t)
    assert mask.all() and min(np.linalg.norm(found - tn), np.linalg.norm(found + tn)) < 1e-3
    assert verify.triangulated_depth(x1, x2, R, t) == pytest.approx(
        float(np.median(np.linalg.norm(X1, axis=1)))
    )
    wrong = ypr_to_matrix(40, -60, 0).T @ ypr_to_matrix(15, -85, 0)
    assert verify.fit_translation(x1, x2, wrong, 1.0)[1].mean() < 0.5


# -- georeference status -----------------------------------------------------------------------
def _georef(residuals: list[float], attitude: float = 1.0, method: str = "LO-RANSAC on centres") -> Georef:
    names = [f"aerial/{i}.jpg" for i in range(len(residuals))]
    geo = Georef(1.0, np.eye(3), np.zeros(3), method, {"max_error_m": 1.5, "rotation_uncertainty_deg": 20.0})
    for n, r in zip(names, residuals, strict=True):
        geo.residuals[n] = np.array([r, 0.0, 0.0])
        geo.inliers[n] = r <= 1.5
        geo.attitude_deg[n] = attitude
    return geo


def test_georef_status():
    assert status(_georef([0.5, 0.8, 1.0, 0.3])) == ("ok", [])
    state, reasons = status(_georef([0.5, 0.8, 1.0, 9.0, 12.0, 11.0, 10.0]))
    assert state == "suspect" and "only 3 of 7 cameras lie within 1.5 m" in reasons[0]
    assert "mean residual 6.33 m" in reasons[1]
    assert status(_georef([0.5, 0.8, 1.0], attitude=25.0))[1] == [
        "camera attitudes are 25.0 degrees off the POS (median)"
    ]
    assert (
        "uncertain by 20.0 degrees" in status(_georef([0.5] * 3, method="LO-RANSAC (ill-conditioned)"))[1][0]
    )
    # the audit's ALIKED run: 0 of 5 cameras within the threshold, residuals 9 m
    state, reasons = status(_georef([9.4, 13.5, 6.2, 6.7, 10.0]))
    assert state == "failed" and reasons == ["only 0 of 5 cameras lie within 1.5 m of their POS"]


def test_the_command_warns_of_a_suspect_georeference(tmp_path, monkeypatch):
    import services.sfm

    def fake_main(conf, images, out, pos, cams):
        georef = {
            "status": "suspect",
            "reasons": ["only 4 of 9 cameras lie within 1.5 m of their POS"],
            "residual_m": {"mean": 3.2, "max": 8.0},
        }
        crs = {"pos": None, "output": None, "files": ["cameras.geojson"]}
        report = {"NRI": "9/9", "num_points3D": 10, "mean_reprojection_error_px": 0.5, "unregistered": []}
        (out / "report.json").write_text(json.dumps({**report, "georef": georef, "crs": crs}))
        return out / "sparse"

    monkeypatch.setattr(services.sfm, "main", fake_main)
    (tmp_path / "images").mkdir()
    (tmp_path / "out").mkdir()
    r = CliRunner().invoke(_app(), ["sfm", str(tmp_path / "images"), str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert "georef residual mean 3.20 m / max 8.00 m (suspect)" in r.output
    assert "warning: the georeference is suspect:\n  only 4 of 9 cameras lie within 1.5 m" in r.output


# -- end to end --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_stations(tmp_path_factory):
    """`tiny` with one line of two stations (10 aerial images): each station's five images share its
    position, so with four stations a similarity always fits one station's five; with two, swapping the
    nadirs' positions leaves none that fits three."""
    import copy

    from services import synth

    conf = copy.deepcopy(synth.confs["tiny"])
    conf["aerial"]["grid"] = [2, 1]
    return synth.main(conf, tmp_path_factory.mktemp("two-stations") / "scene", seed=0)


def test_a_failed_georeference_exits_non_zero_and_keeps_the_model(two_stations, tmp_path):
    """The two nadir images' POS positions swapped: no similarity fits 3 of the cameras."""
    tiny_scene = two_stations
    recs = read_pos_csv(tiny_scene / "pos.csv")
    by = {r.name: r for r in recs}
    a, b = by["aerial/A0001.jpg"], by["aerial/A0006.jpg"]  # the nadir images swap stations
    (a.lat, a.lon, a.h), (b.lat, b.lon, b.h) = (b.lat, b.lon, b.h), (a.lat, a.lon, a.h)
    pos = write_pos_csv(tmp_path / "pos.csv", recs)
    out = tmp_path / "sfm"
    conf = {"mapping": {"use_prior_position": False}, "verify": {"check": False}}
    with pytest.raises(GeorefError, match="georeferencing failed: only"):
        main({**confs["sift"], **conf}, tiny_scene / "images", out, pos, None)
    report = json.loads((out / "report.json").read_text())
    assert report["georef"]["status"] == "failed" and report["georef"]["reasons"]
    assert pycolmap.Reconstruction(str(out / "sparse")).num_reg_images() >= 3  # the model is kept
    assert json.loads((out / "georef.json").read_text())["summary"]["status"] == "failed"
    assert not (out / "cameras.geojson").exists()
    args = ["sfm", str(tiny_scene / "images"), str(tmp_path / "cli"), "--pos", str(pos), "--no-priors"]
    r = CliRunner().invoke(_app(), args)
    assert r.exit_code == 2, r.output
    assert "georeferencing failed" in r.output and "The model is kept in" in r.output
    assert "(failed)" in r.output  # the summary line still prints


@pytest.mark.slow
def test_aliked_on_the_tiny_scene(tiny_scene, tmp_path):
    """ALIKED + LightGlue on all pairs (the audit's run: NRI 5/10 of a broken model, 0/5 georef
    inliers, 9 m residuals). Nadir images 180 degrees apart (serpentine flight) match once turned north
    up; the wrong pairs of opposite obliques are removed; all 20 images register (as with SIFT) and
    georeference within the POS noise; the feature and matching times are measured each."""
    out = tmp_path / "sfm"
    r = CliRunner().invoke(_app(), ["sfm", str(tiny_scene), str(out), "--features", "aliked"])
    assert r.exit_code == 0, r.output
    assert "the georeference is" not in r.output  # no CLI warning about the georeference
    report = json.loads((out / "report.json").read_text())
    registered = {im.name for im in pycolmap.Reconstruction(str(out / "sparse")).images.values()}
    assert len(registered) == report["num_registered"] == 20
    g = report["georef"]
    assert g["status"] == "ok" and g["num_inliers"] == g["num_images"] == report["num_registered"]
    assert g["residual_m"]["max"] < 2.0 and g["attitude_deg"]["median"] < 5.0
    from services.sfm.report import compare_with_truth

    truth = compare_with_truth(out, tiny_scene)
    assert truth["absolute_m"]["max"] < 1.5 and truth["aligned_m"]["max"] < 0.5
    db = pycolmap.Database.open(str(out / "database.db"))
    ids = {im.name: im.image_id for im in db.read_all_images()}
    nadirs = db.read_two_view_geometry(ids["aerial/A0001.jpg"], ids["aerial/A0016.jpg"])  # 180 deg apart
    db.close()
    assert len(nadirs.inlier_matches) >= 100  # unturned, LightGlue finds no correct match there
    t = report["timings_s"]
    assert t["features"] > 0 and t["matching"] > 0 and t["features"] != t["matching"]
    turns = report["aliked"]["turns"]
    assert turns["aerial/A0011.jpg"] == turns["aerial/A0016.jpg"] == 2  # the second line's nadir images
    assert report["pair_check"]["rejected"] and report["pairing"] == "exhaustive (190 pairs)"
