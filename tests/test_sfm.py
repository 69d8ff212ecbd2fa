"""Aerial SfM: georeferencing, footprints, report reasons, inputs, and a small end-to-end run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from cli.sfm import sfm as sfm_command
from services.pos import (
    CRSError,
    LocalFrame,
    PosError,
    PosRecord,
    from_wgs84,
    matrix_to_ypr,
    read_pos,
    read_pos_csv,
    to_wgs84,
    write_pos_csv,
    ypr_to_matrix,
)
from services.sfm import GeorefError, confs, export, main
from services.sfm.aerial import prepare_images, select_records, verify_images
from services.sfm.geojson import camera_features, footprint
from services.sfm.georef import condition, estimate
from services.sfm.report import compare_with_truth, unregistered_reason
from shared.images import ImageError

BRIGHTON = Path(__file__).resolve().parents[2] / "shared" / "data" / "brighton_beach" / "images"


def _rot(axis_angle) -> np.ndarray:
    return pycolmap.Rotation3d(np.asarray(axis_angle, float)).matrix()


# -- georeferencing ----------------------------------------------------------------------------
def test_georef_recovers_a_similarity_and_flags_outliers():
    rng = np.random.default_rng(0)
    tgt = np.c_[rng.uniform(-50, 50, (20, 2)), rng.normal(0, 0.3, 20)]  # one flight height: coplanar
    R, s, t = _rot([0.1, -0.2, 1.2]), 0.05, np.array([3.0, -1.0, 7.0])
    src = ((tgt - t) @ R) / s  # tgt = s R src + t
    noisy = tgt + rng.normal(0, 0.2, tgt.shape)
    noisy[3] += [15.0, 0.0, 0.0]  # one bad GPS fix
    names = [f"aerial/{i}.jpg" for i in range(20)]
    geo = estimate(names, src, noisy, sigma=0.3)
    assert geo.scale == pytest.approx(s, rel=0.01)
    assert np.degrees(np.arccos((np.trace(geo.R.T @ R) - 1) / 2)) < 0.5
    assert geo.condition["coplanar"] and not geo.condition["ill_conditioned"]
    assert not geo.inliers[names[3]] and sum(geo.inliers.values()) == 19
    assert np.linalg.norm(geo.residuals[names[3]]) == pytest.approx(15.0, abs=1.0)


def test_georef_collinear_centres_take_the_rotation_from_attitudes():
    rng = np.random.default_rng(1)
    n = 8
    tgt = np.c_[np.linspace(0, 70, n), rng.normal(0, 0.05, n), rng.normal(40, 0.05, n)]  # one flight line
    R, s, t = _rot([0.3, 0.2, -0.7]), 2.0, np.array([1.0, 2.0, 3.0])
    src = ((tgt - t) @ R) / s
    R_pos = [ypr_to_matrix(90 + rng.normal(0, 1), -90 + rng.normal(0, 1), 0) for _ in range(n)]
    R_rec = [R.T @ Rp for Rp in R_pos]  # the reconstruction's R_world_from_cam in its own frame
    R_pos_noisy = list(R_pos)
    R_pos_noisy[2] = ypr_to_matrix(270, -90, 0)  # one attitude 180 degrees off
    names = [f"aerial/{i}.jpg" for i in range(n)]
    assert condition(tgt, 0.5)["collinear"]
    geo = estimate(names, src, tgt, 0.5, R_rec, R_pos_noisy)
    assert "attitudes" in geo.method and "7/8" in geo.method
    assert np.degrees(np.arccos(np.clip((np.trace(geo.R.T @ R) - 1) / 2, -1, 1))) < 0.5
    assert geo.attitude_deg[names[2]] > 170 and geo.attitude_deg[names[0]] < 0.5
    without = estimate(names, src, tgt, 0.5)
    assert "ill-conditioned" in without.method
    with pytest.raises(GeorefError, match="needs 3"):
        estimate(names[:2], src[:2], tgt[:2], 0.5)


def _level_flight(seed: int, n: int = 40, att_noise_deg: float = 1.0):
    """A survey flown at one altitude (nadir, small pitch and roll), its reconstruction (an arbitrary
    similarity away) and a POS with 0.5 m horizontal, 0.8 m vertical and att_noise_deg attitude noise."""
    rng = np.random.default_rng(seed)
    C = np.c_[rng.uniform(-40, 40, (n, 2)), 60 + rng.normal(0, 0.4, n)]
    tilts = rng.normal(0, np.radians(3), (n, 3)) * [1, 1, 0]  # camera-frame pitch and roll, 3 degrees
    R_true = [ypr_to_matrix(rng.uniform(0, 360), -90, 0) @ _rot(w) for w in tilts]
    R, s, t = _rot([0.4, -1.1, 2.0]), 0.3, np.array([4.0, -2.0, 1.0])
    src = ((C - t) @ R) / s
    R_rec = [R.T @ Rt for Rt in R_true]
    tgt = C + rng.normal(0, 1, (n, 3)) * [0.5, 0.5, 0.8]
    R_pos = [Rt @ _rot(rng.normal(0, np.radians(att_noise_deg), 3)) for Rt in R_true]
    return [f"aerial/{i}.jpg" for i in range(n)], src, tgt, R_rec, R_pos, (s, R, t)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_georef_joint_fit_fixes_the_tilt_of_a_flight_at_one_altitude():
    names, src, tgt, R_rec, R_pos, (s, R, t) = _level_flight(3, 60)
    n = len(names)
    std = np.tile([0.5, 0.5, 0.8], (n, 1))
    before = estimate(names, src, tgt, 0.5, R_rec, R_pos, conf={"joint": False})
    after = estimate(names, src, tgt, 0.5, R_rec, R_pos, pos_std=std, att_std_deg=np.full(n, 1.0))
    err_before, err_after = _angle_deg(before.R.T @ R), _angle_deg(after.R.T @ R)
    # the centres alone fix the tilt to about 0.8 m over the flight's extent; 60 attitudes of 1 degree
    # to about 1 / sqrt(60) = 0.13 degrees per axis
    assert err_before > 0.4 and err_after < 0.3
    assert "joint refinement (centres, 60 attitudes)" in after.method
    u = after.uncertainty
    assert 0.05 < u["tilt_deg"] < 0.3 and err_after < 3 * np.sqrt(u["tilt_deg"] ** 2 + u["heading_deg"] ** 2)
    assert after.scale == pytest.approx(s, rel=0.005)
    assert after.noise["position_source"] == "stated" and sum(after.inliers.values()) >= n - 2


def test_georef_joint_fit_estimates_unstated_noise_and_uses_an_orientation_prior():
    """No attitudes and no stated std (EXIF GPS): the noise comes from the residuals and the tilt from
    the flight's own plane (flown at one height: "level"), or, asked for, from the cameras' own axes (a
    nadir flight: the x and y axes horizontal, "vertical")."""
    names, src, tgt, R_rec, _, (s, R, t) = _level_flight(3, 60)
    n = len(names)
    tgt = tgt.copy()
    tgt[:, 2] += np.linspace(-15, 15, n) * np.sign(
        src @ R.T[:, 0] - (src @ R.T[:, 0]).mean()
    )  # bad GPS heights
    unstated = np.full((n, 3), np.nan)
    for kind, bound in (("level", 0.5), ("vertical", 1.5)):
        conf = {"orientation_prior": "auto" if kind == "level" else kind}
        geo = estimate(names, src, tgt, 3.0, R_rec, None, conf=conf, pos_std=unstated)
        assert geo.noise["orientation_prior"] == kind and geo.noise["position_source"] == "estimated"
        assert geo.noise["vertical_m"] > 3 * geo.noise["horizontal_m"]  # the heights' noise is seen
        up = geo.R @ R.T @ np.array([0.0, 0.0, 1.0])  # the true up in the georeferenced frame
        assert np.degrees(np.arccos(up[2])) < bound, kind
        assert geo.levels["flight_plane_tilt_deg"] < 1.0
    centres_only = estimate(names, src, tgt, 3.0, conf={"joint": False})
    up0 = centres_only.R @ R.T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(up0[2])) > 5  # the heights tilt a fit on the centres alone


def test_georef_joint_fit_takes_the_heading_from_the_centres_when_the_compass_is_biased():
    """Attitudes whose headings share a 3 degree offset (a consumer drone's compass): the fit frees that
    offset, and the heading comes from the centres; the tilt still from the attitudes."""
    names, src, tgt, R_rec, R_pos, (s, R, t) = _level_flight(5, 60)
    bias = _rot([0.0, 0.0, np.radians(3.0)])
    R_biased = [bias @ Rp for Rp in R_pos]
    n = len(names)
    std = np.tile([0.5, 0.5, 0.8], (n, 1))
    geo = estimate(names, src, tgt, 0.5, R_rec, R_biased, pos_std=std, att_std_deg=np.full(n, 1.0))
    yaw = geo.noise["attitude_yaw"]
    assert yaw["biased"] and yaw["bias_deg"] == pytest.approx(3.0, abs=0.5), yaw
    assert "headings" in geo.method and _angle_deg(geo.R.T @ R) < 0.4
    unbiased = estimate(names, src, tgt, 0.5, R_rec, R_pos, pos_std=std, att_std_deg=np.full(n, 1.0))
    assert not unbiased.noise["attitude_yaw"]["biased"]


# -- footprints and GeoJSON --------------------------------------------------------------------
def _nadir_reconstruction() -> pycolmap.Reconstruction:
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=200, height=100, params=[100, 100, 100, 50], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    R_wc = ypr_to_matrix(0, -90, 0)  # nadir, image top north
    c = np.array([10.0, 20.0, 50.0])
    img = pycolmap.Image(name="aerial/A.jpg", camera_id=1, image_id=1)
    rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R_wc.T), -R_wc.T @ c))
    return rec


def test_footprint_of_a_nadir_camera():
    rec = _nadir_reconstruction()
    fp = footprint(rec.images[1], ground_z=0.0)
    # 50 m above the ground, f = 100 px: 200 x 100 px cover 100 m (east) x 50 m (north)
    np.testing.assert_allclose(fp[:, :2].min(0), [10 - 50, 20 - 25], atol=1e-9)
    np.testing.assert_allclose(fp[:, :2].max(0), [10 + 50, 20 + 25], atol=1e-9)
    np.testing.assert_allclose(fp[0, :2], [10 - 50, 20 + 25], atol=1e-9)  # top-left corner is north-west
    assert footprint(rec.images[1], ground_z=60.0) is None  # the plane is behind the camera
    frame = LocalFrame(46.84, -91.99, 200.0)
    fc = camera_features(rec, frame, {"aerial/A.jpg": 0.3}, ground_z=0.0)
    point, poly = fc["features"]
    assert point["geometry"]["type"] == "Point" and point["properties"]["residual"] == 0.3
    lon, lat, h = point["geometry"]["coordinates"]
    np.testing.assert_allclose(frame.from_wgs84(lat, lon, h)[0], [10, 20, 50], atol=1e-6)
    ring = np.array(poly["geometry"]["coordinates"][0])
    assert len(ring) == 5 and np.all(ring[0] == ring[-1])
    x, y = ring[:-1, 0], ring[:-1, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0  # counter-clockwise (RFC 7946)
    assert poly["properties"] | {"set": "aerial", "kind": "footprint"} == poly["properties"]


def _camera_at(rec: pycolmap.Reconstruction, image_id: int, R_wc: np.ndarray, c: np.ndarray) -> None:
    img = pycolmap.Image(name=f"aerial/{image_id}.jpg", camera_id=1, image_id=image_id)
    rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R_wc.T), -R_wc.T @ c))


def test_output_crs_resolution():
    assert export.resolve_crs("auto", "EPSG:32633") == "EPSG:32633"
    assert export.resolve_crs("auto", "EPSG:4979") is None and export.resolve_crs("auto", None) is None
    assert export.resolve_crs("auto", "EPSG:4326") is None
    assert export.resolve_crs("auto", "EPSG:4258") == "EPSG:4258"  # ETRS89 lat/lon: not WGS84
    assert export.resolve_crs("none", "EPSG:32633") is None and export.resolve_crs(None, "EPSG:32633") is None
    assert export.resolve_crs("EPSG:25833", None) == "EPSG:25833"
    with pytest.raises(CRSError):
        export.resolve_crs("EPSG:999999", None)


def test_camera_positions_round_trip_in_utm(tmp_path):
    """Cameras placed at known UTM 33N coordinates come out at those coordinates in cameras.csv and in
    the projected GeoJSON, and read back (read_pos) to the same WGS84 positions and attitudes."""
    known = np.array([[500100.0, 6170200.0, 80.0], [500160.0, 6170180.0, 82.0], [499950.0, 6169900.0, 78.5]])
    lat, lon, h = to_wgs84("EPSG:32633", *known.T)
    frame = LocalFrame(float(lat.mean()), float(lon.mean()), float(h.mean()))
    rec = _nadir_reconstruction()
    rec.deregister_frame(rec.images[1].frame_id)
    atts = [ypr_to_matrix(0, -90, 0), ypr_to_matrix(90, -45, 0), ypr_to_matrix(200, -60, 3)]
    for k, (a, b, c) in enumerate(zip(lat, lon, h, strict=True)):
        _camera_at(rec, 2 + k, frame.rotation_to_enu_at(a, b).T @ atts[k], frame.from_wgs84(a, b, c)[0])
    export.main({"out_crs": "auto"}, rec, frame, tmp_path, pos_crs="EPSG:32633", ground_z=-80.0)
    text = (tmp_path / "cameras.csv").read_text()
    assert "# crs: EPSG:32633" in text and "name,x,y,z,yaw,pitch,roll" in text
    rows = [ln.split(",") for ln in text.splitlines()[4:]]
    got = np.array([[float(v) for v in r[1:4]] for r in rows])
    np.testing.assert_allclose(got, known, atol=1e-3)
    back = read_pos(tmp_path / "cameras.csv")
    assert [r.name for r in back] == ["aerial/2.jpg", "aerial/3.jpg", "aerial/4.jpg"]
    for r, a, b, R in zip(back, lat, lon, atts, strict=True):
        assert (r.lat, r.lon, r.crs) == (pytest.approx(a, abs=1e-9), pytest.approx(b, abs=1e-9), "EPSG:32633")
        np.testing.assert_allclose(r.R_world_from_cam, R, atol=1e-4)
    assert matrix_to_ypr(back[2].R_world_from_cam)[0] == pytest.approx(200.0, abs=1e-3)
    fc = json.loads((tmp_path / "cameras.epsg32633.geojson").read_text())
    assert fc["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32633"
    points = [f["geometry"]["coordinates"] for f in fc["features"] if f["properties"]["kind"] == "camera"]
    np.testing.assert_allclose(points, known, atol=1e-3)
    (poly,) = [f for f in fc["features"] if f["properties"]["name"] == "aerial/2.jpg"][1:]
    ring = np.array(poly["geometry"]["coordinates"][0])  # nadir, about 80 m up, f = 100 px: 160 x 80 m
    assert np.ptp(ring[:, 0]) == pytest.approx(160.0, rel=0.01) and np.ptp(ring[:, 1]) == pytest.approx(
        80, rel=0.01
    )
    wgs = json.loads((tmp_path / "cameras.geojson").read_text())
    assert "crs" not in wgs and len(wgs["features"]) == len(fc["features"])
    export.main({"out_crs": "auto"}, rec, frame, tmp_path, pos_crs="EPSG:4979")
    assert not (tmp_path / "cameras.csv").exists()  # WGS84 POS: WGS84 outputs only, stale files removed
    assert not (tmp_path / "cameras.epsg32633.geojson").exists()


def test_unregistered_reasons():
    g = {
        "a": {"keypoints": 0, "pairs": 0, "max_inliers": 0},
        "b": {"keypoints": 900, "pairs": 0, "max_inliers": 0},
        "c": {"keypoints": 900, "pairs": 2, "max_inliers": 40},
    }
    assert unregistered_reason("a", g, {}) == "no features detected"
    assert "no geometrically verified image pair" in unregistered_reason("b", g, {})
    assert "separate, smaller model #1" in unregistered_reason("c", g, {"c": 1})
    assert "2 verified pairs, best 40 inliers" in unregistered_reason("c", g, {})
    assert "not in the database" in unregistered_reason("z", g, {})


# -- inputs ------------------------------------------------------------------------------------
def _jpeg(path: Path, size=(32, 24)) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((size[1], size[0], 3), 128, np.uint8)).save(path)
    return path


def test_flat_and_nested_image_folders(tmp_path):
    for n in ("b.jpg", "a.JPG"):
        _jpeg(tmp_path / "flat" / n)
    root, names = prepare_images(tmp_path / "flat", tmp_path / "out")
    assert names == ["aerial/a.JPG", "aerial/b.jpg"] and root == tmp_path / "out" / "images"
    assert (root / names[0]).is_file() and (root / "aerial").is_symlink()
    root2, names2 = prepare_images(tmp_path / "flat", tmp_path / "out")  # again: the link is replaced
    assert names2 == names
    _jpeg(tmp_path / "images" / "aerial" / "x.jpg")
    _jpeg(tmp_path / "images" / "ground" / "g.jpg")
    root, names = prepare_images(tmp_path / "images", tmp_path / "out2")
    assert root == tmp_path / "images" and names == ["aerial/x.jpg"]


def test_bad_images_and_pos_are_named(tmp_path):
    d = tmp_path / "images" / "aerial"
    for n in ("a.jpg", "b.jpg", "c.jpg"):
        _jpeg(d / n)
    data = (d / "c.jpg").read_bytes()
    (d / "c.jpg").write_bytes(data[: len(data) - 40])
    with pytest.raises(ImageError, match=r"1 unusable image\(s\):\n.*c.jpg: truncated JPEG"):
        verify_images(tmp_path / "images", ["aerial/a.jpg", "aerial/b.jpg", "aerial/c.jpg"])
    recs = [
        PosRecord("aerial/a.jpg", 55.0, 13.0, 50.0),
        PosRecord("ground/g.jpg", 55.0, 13.0, 2.0),
        PosRecord("aerial/z.jpg", 55.0, 13.0, 50.0),
    ]
    with pytest.raises(PosError) as e:
        select_records(recs, ["aerial/a.jpg", "aerial/b.jpg"])
    assert "image 'aerial/b.jpg' has no POS row" in str(e.value)
    assert "POS row 'aerial/z.jpg' names no uploaded image" in str(e.value)
    assert "ground/g.jpg" not in str(e.value)  # other sets are not the aerial SfM's business
    # through the command: exit code 2 and the message
    app = typer.Typer()
    app.command("sfm")(sfm_command)
    app.command("other")(lambda: None)
    write_pos_csv(tmp_path / "pos.csv", recs[:1])
    r = CliRunner().invoke(
        app, ["sfm", str(tmp_path / "images"), str(tmp_path / "out"), "--pos", str(tmp_path / "pos.csv")]
    )
    assert r.exit_code == 2 and "c.jpg: truncated JPEG" in r.output


# -- end to end --------------------------------------------------------------------------------
def test_sfm_on_the_tiny_synthetic_scene(tiny_scene, tmp_path):
    """The tiny preset: a 2 x 2 grid of stations of one nadir and four outward obliques (-45 deg) each;
    all 20 register, georeferenced within the POS noise."""
    app = typer.Typer()
    app.command("sfm")(sfm_command)
    app.command("other")(lambda: None)
    out = tmp_path / "sfm"
    r = CliRunner().invoke(app, ["sfm", str(tiny_scene), str(out)])  # a scene folder: pos.csv, cameras.json
    assert r.exit_code == 0, r.output
    report = json.loads((out / "report.json").read_text())
    registered = {im.name for im in pycolmap.Reconstruction(str(out / "sparse")).images.values()}
    assert report["num_registered"] == report["num_images"] == len(registered) == 20
    assert report["unregistered"] == []
    assert report["mean_reprojection_error_px"] < 1.0
    g = report["georef"]
    assert g["residual_m"]["max"] < 2.0 and g["attitude_deg"]["median"] < 3.0
    truth = compare_with_truth(out, tiny_scene)
    assert truth["absolute_m"]["max"] < 1.5  # POS noise: 0.5 m horizontal, 0.8 m vertical
    assert truth["aligned_m"]["max"] < 0.3
    geo = json.loads((out / "cameras.geojson").read_text())
    assert sum(f["properties"]["kind"] == "camera" for f in geo["features"]) == report["num_registered"]
    georef = json.loads((out / "georef.json").read_text())
    assert (
        set(georef["frame"]) >= {"lat0", "lon0", "h0"} and len(georef["images"]) == report["num_registered"]
    )
    assert set(report["timings_s"]) >= {"features", "matching", "mapping", "georef"}
    assert georef["crs"] == {"pos": "EPSG:4979", "output": None, "files": ["cameras.geojson"]}
    assert not (out / "cameras.csv").exists()  # a WGS84 POS: WGS84 outputs only


def test_sfm_writes_cameras_in_the_pos_crs(tiny_scene, tmp_path):
    """The tiny scene's POS given in UTM 33N: cameras.csv comes out in UTM 33N, within the POS noise of
    the POS coordinates, and georef.json and report.json record both CRSs."""
    utm = write_pos_csv(tmp_path / "pos-utm.csv", read_pos_csv(tiny_scene / "pos.csv"), crs="EPSG:32633")
    app = typer.Typer()
    app.command("sfm")(sfm_command)
    app.command("other")(lambda: None)
    out = tmp_path / "sfm"
    r = CliRunner().invoke(app, ["sfm", str(tiny_scene), str(out), "--pos", str(utm)])
    assert r.exit_code == 0, r.output
    assert "camera positions in EPSG:32633" in r.output and "cameras.epsg32633.geojson" in r.output
    georef = json.loads((out / "georef.json").read_text())
    assert georef["crs"]["pos"] == georef["crs"]["output"] == "EPSG:32633"
    assert json.loads((out / "report.json").read_text())["crs"]["output"] == "EPSG:32633"
    pos = {r.name: r for r in read_pos(utm)}
    got = read_pos(out / "cameras.csv")
    assert len(got) >= 4 and {r.crs for r in got} == {"EPSG:32633"}
    lines = (out / "cameras.csv").read_text().splitlines()
    assert lines[1] == "# crs: EPSG:32633" and lines[3].startswith("name,x,y,z")
    for row in lines[4:]:
        name, x, y, z = row.split(",")[:4]
        ref = np.array(from_wgs84("EPSG:32633", pos[name].lat, pos[name].lon, pos[name].h), float)
        assert np.linalg.norm(np.array([float(x), float(y), float(z)]) - ref) < 2.0  # POS noise 0.5/0.8 m
    r = CliRunner().invoke(app, ["sfm", str(tiny_scene), str(tmp_path / "bad"), "--out-crs", "EPSG:999999"])
    assert r.exit_code == 2 and "unknown CRS 'EPSG:999999'" in r.output


@pytest.mark.skipif(not BRIGHTON.is_dir(), reason=f"shared data absent: {BRIGHTON}")
def test_sfm_on_downscaled_dji_images_with_exif(tmp_path):
    """Six brighton_beach images (two flight lines) downscaled with their EXIF and XMP: POS from EXIF."""
    flat = tmp_path / "flat"
    flat.mkdir()
    for n in ("DJI_0019", "DJI_0020", "DJI_0021", "DJI_0032", "DJI_0033", "DJI_0034"):
        with Image.open(BRIGHTON / f"{n}.JPG") as im:
            xmp = (BRIGHTON / f"{n}.JPG").read_bytes()
            i, j = xmp.find(b"<x:xmpmeta"), xmp.find(b"</x:xmpmeta>") + 12
            im.resize((1000, 562)).save(flat / f"{n}.JPG", quality=90, exif=im.info["exif"], xmp=xmp[i:j])
    conf = {**confs["sift"], "features": {**confs["sift"]["features"], "max_image_size": 1000}}
    sparse = main(conf, flat, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["NRI"] == "6/6", report["unregistered"]
    assert report["pos_source"] == "exif" and report["camera_prior"] == "exif"
    assert report["georef"]["residual_m"]["max"] < 3.0
    rec = pycolmap.Reconstruction(str(sparse))
    assert {im.name for im in rec.images.values()} == {f"aerial/{p.name}" for p in flat.iterdir()}
