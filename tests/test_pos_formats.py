"""POS formats besides the CSV: ODM geo.txt, JSON, image EXIF/XMP, and the `read_pos` dispatcher."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.pos import (
    CRSError,
    LocalFrame,
    PosError,
    PosRecord,
    camera_from_exif,
    check_image,
    from_wgs84,
    image_paths,
    matrix_to_ypr,
    parse_crs_line,
    parse_geo_txt,
    parse_pos_json,
    read_exif,
    read_pos,
    read_pos_exif,
    to_wgs84,
    write_geo_txt,
    write_pos_csv,
    write_pos_json,
    ypr_to_matrix,
)
from shared.images import ImageError

BRIGHTON = Path(__file__).resolve().parents[2] / "shared" / "data" / "brighton_beach" / "images"
needs_brighton = pytest.mark.skipif(not BRIGHTON.is_dir(), reason=f"shared data absent: {BRIGHTON}")


# -- coordinates -------------------------------------------------------------------------------
def test_projected_point_against_its_wgs84_value():
    # UTM 33N: the central meridian is 15 E; easting 500000 lies on it
    lat, lon, h = to_wgs84("EPSG:32633", np.array([500000.0]), np.array([6000000.0]), np.array([10.0]))
    assert lon[0] == pytest.approx(15.0, abs=1e-9)
    assert lat[0] == pytest.approx(54.1481041, abs=1e-6)
    x, y, z = from_wgs84("EPSG:32633", lat, lon, h)
    np.testing.assert_allclose([x[0], y[0], z[0]], [500000.0, 6000000.0, 10.0], atol=1e-4)


def test_enu_of_a_point_north_and_east():
    f = LocalFrame(46.8426, -91.9940, 198.0)
    north = f.from_wgs84(46.8436, -91.9940, 198.0)[0]
    assert north[1] == pytest.approx(111.2, abs=0.3) and abs(north[0]) < 1e-6
    east = f.from_wgs84(46.8426, -91.9930, 198.0)[0]  # 0.001 deg of longitude ~ 111 m * cos(lat)
    assert east[0] == pytest.approx(111.3 * np.cos(np.radians(46.8426)), abs=0.3)


def test_crs_lines():
    assert parse_crs_line("EPSG:4326") == "EPSG:4326"
    assert parse_crs_line("WGS84 UTM 16N") == "EPSG:32616"
    assert parse_crs_line("WGS84 UTM 33s") == "EPSG:32733"
    assert parse_crs_line("+proj=utm +zone=10 +ellps=WGS84 +datum=WGS84 +units=m +no_defs").startswith(
        "+proj"
    )
    for bad in ("EPSG:999999", "WGS84 UTM 61N", "nonsense"):
        with pytest.raises(CRSError):
            parse_crs_line(bad)


# -- ODM geo.txt -------------------------------------------------------------------------------
GEO = """EPSG:4326
DJI_0028.JPG -91.9942096111111 46.84252125 198.609
DJI_0032.JPG -91.9938293055556 46.8424584444444 198.609 45 0 0 1.5 3.0
"""


def test_geo_txt_geographic_is_lon_lat():
    recs = parse_geo_txt(GEO)
    assert [r.name for r in recs] == ["DJI_0028.JPG", "DJI_0032.JPG"]
    assert recs[0].lat == pytest.approx(46.84252125) and recs[0].lon == pytest.approx(-91.9942096111111)
    assert recs[0].h == pytest.approx(198.609) and recs[0].R_world_from_cam is None
    assert (recs[1].std_xy, recs[1].std_z) == (1.5, 3.0)
    # ODM's angles: pitch 0 is nadir, yaw the heading of the image top
    yaw, pitch, _ = matrix_to_ypr(recs[1].R_world_from_cam)
    assert (yaw, pitch) == (pytest.approx(45.0), pytest.approx(-90.0))


def test_geo_txt_gimbal_angles_and_zero_angles():
    text = "EPSG:4326\na.jpg -91.99 46.84 198 90 -60 0\nb.jpg -91.99 46.85 198 0 0 0\n"
    a, b = parse_geo_txt(text)  # a pitch below -45: gimbal convention (auto)
    np.testing.assert_allclose(a.R_world_from_cam, ypr_to_matrix(90, -60, 0), atol=1e-12)
    assert b.R_world_from_cam is None  # 0 0 0: "not available" in ODM's docs
    a2, _ = parse_geo_txt(text, pitch_zero="nadir")
    np.testing.assert_allclose(a2.R_world_from_cam, ypr_to_matrix(90, -150, 0), atol=1e-12)


def test_geo_txt_projected_and_round_trip(tmp_path):
    recs = [
        PosRecord("aerial/A.jpg", 54.148, 15.001, 120.0, ypr_to_matrix(30, -80, 2), 0.5, 1.0),
        PosRecord("aerial/B.jpg", 54.149, 15.002, 121.0),
    ]
    for crs in ("EPSG:32633", "EPSG:4326"):
        path = write_geo_txt(tmp_path / "geo.txt", recs, crs=crs)
        back = read_pos(path)
        f = LocalFrame(54.148, 15.001, 120.0)
        for a, b in zip(recs, back, strict=True):
            assert a.name == b.name
            np.testing.assert_allclose(
                f.from_wgs84(b.lat, b.lon, b.h), f.from_wgs84(a.lat, a.lon, a.h), atol=1e-3
            )
        np.testing.assert_allclose(back[0].R_world_from_cam, recs[0].R_world_from_cam, atol=1e-6)
        assert back[1].R_world_from_cam is None


def test_readers_keep_the_input_crs(tmp_path):
    recs = _recs()
    assert {r.crs for r in read_pos(write_geo_txt(tmp_path / "geo.txt", recs, crs="EPSG:32633"))} == {
        "EPSG:32633"
    }
    assert {r.crs for r in parse_geo_txt("WGS84 UTM 33N\na.jpg 500000 6170000 80\n")} == {"EPSG:32633"}
    for crs in ("EPSG:4979", "EPSG:25833"):
        assert {r.crs for r in read_pos(write_pos_json(tmp_path / "p.json", recs, crs=crs))} == {crs}
        assert {r.crs for r in read_pos(write_pos_csv(tmp_path / "p.csv", recs, crs=crs))} == {crs}


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("a.jpg -91.99 nan 198\n", "line 2, column lat: 'nan' is not finite"),
        ("a.jpg 191.99 46.8 198\n", "column lon: 191.99 is outside"),
        ("a.jpg -91.99 46.8 198\na.jpg -91.99 46.8 198\n", "duplicate name 'a.jpg'"),
        ("a.jpg -91.99\n", "expected `name x y [z] ...`"),
        ("a.jpg -91.99 46.8 198 10\n", "give yaw, pitch and roll together"),
        ("a.jpg -91.99 46.8 198 0 0 0 -1 2\n", "column horizontal accuracy: -1.0 is outside"),
        ("a.jpg -91.99 46.8 x\n", "column z: 'x' is not a number"),
    ],
)
def test_geo_txt_bad_lines(body, message):
    with pytest.raises(PosError) as e:
        parse_geo_txt("EPSG:4326\n" + body, source="geo.txt")
    assert message in str(e.value)


def test_geo_txt_unknown_crs():
    with pytest.raises(PosError, match="line 1: unknown CRS 'EPSG:999999'"):
        parse_geo_txt("EPSG:999999\na.jpg 1 2 3\n", source="geo.txt")


# -- JSON --------------------------------------------------------------------------------------
def _recs() -> list[PosRecord]:
    return [
        PosRecord("aerial/A0001.jpg", 55.7047, 13.1910, 130.5, ypr_to_matrix(90, -45, 0), 0.5, 1.0, 1.5),
        PosRecord("aerial/A0002.jpg", 55.7049, 13.1913, 131.8, None, 3.0, 5.0),
    ]


@pytest.mark.parametrize(("crs", "attitude"), [("EPSG:4979", "ypr"), ("EPSG:32633", "opk")])
def test_json_round_trip(tmp_path, crs, attitude):
    path = write_pos_json(tmp_path / "pos.json", _recs(), crs=crs, attitude=attitude)
    back = read_pos(path)
    f = LocalFrame(55.7047, 13.1910, 130.0)
    for a, b in zip(_recs(), back, strict=True):
        np.testing.assert_allclose(
            f.from_wgs84(b.lat, b.lon, b.h), f.from_wgs84(a.lat, a.lon, a.h), atol=1e-3
        )
        assert (b.std_xy, b.std_z, b.std_att) == (a.std_xy, a.std_z, a.std_att)
    np.testing.assert_allclose(back[0].R_world_from_cam, _recs()[0].R_world_from_cam, atol=1e-5)
    assert back[1].R_world_from_cam is None


def test_json_shapes():
    lst = parse_pos_json(
        '[{"name": "aerial/a.jpg", "lat": 55.7, "lon": 13.1, "h": 50, "yaw": 10, "pitch": -90, "roll": 0}]'
    )
    by_name = parse_pos_json('{"aerial/a.jpg": {"LAT": 55.7, "lon": 13.1, "h": 50}}')
    assert lst[0].name == by_name[0].name == "aerial/a.jpg"
    assert lst[0].lat == by_name[0].lat == 55.7


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[{"name": "a", "lat": NaN, "lon": 13.1, "h": 50}]', "record 0, column lat: nan is not finite"),
        ('[{"name": "a", "lat": 55, "lon": 13.1}]', "record 0, column h: missing value"),
        (
            '[{"name": "a", "lat": 55, "lon": 13, "h": 1}, {"name": "a", "lat": 55, "lon": 13, "h": 1}]',
            "duplicate name 'a'",
        ),
        ('{"crs": "EPSG:0", "records": []}', "unknown CRS 'EPSG:0'"),
        (
            '[{"name": "a", "lat": 55, "lon": 13, "h": 1, "yaw": 1000, "pitch": 0, "roll": 0}]',
            "column yaw: 1000.0 is outside",
        ),
        ("[1, 2]", "record 0 is not an object"),
        ("{not json", "not valid JSON"),
    ],
)
def test_json_bad_input(text, message):
    with pytest.raises(PosError) as e:
        parse_pos_json(text)
    assert message in str(e.value)


# -- EXIF / XMP --------------------------------------------------------------------------------
def _rational_dms(deg: float) -> tuple[float, float, float]:
    d = int(deg)
    m = int((deg - d) * 60)
    return (float(d), float(m), (deg - d - m / 60) * 3600)


def write_gps_jpeg(
    path: Path,
    lat: float,
    lon: float,
    alt: float,
    size=(64, 48),
    xmp: str | None = None,
    exif_tags: dict | None = None,
) -> Path:
    """A small JPEG with EXIF GPS (and optionally a DJI-style XMP packet); `exif_tags` replace the Exif
    IFD's (FocalLengthIn35mmFilm 24 by default; None as a value removes the tag)."""
    img = Image.fromarray(np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), np.uint8))
    exif = Image.Exif()
    gps = {
        1: "N" if lat >= 0 else "S",
        2: _rational_dms(abs(lat)),
        3: "E" if lon >= 0 else "W",
        4: _rational_dms(abs(lon)),
        5: 0,
        6: float(alt),
    }
    exif[0x8825] = gps
    exif[0x010F] = "DJI"
    sub = exif.get_ifd(0x8769)
    sub[0xA405] = 24
    for tag, value in (exif_tags or {}).items():
        if value is None:
            sub.pop(tag, None)
        else:
            sub[tag] = value
    kwargs = {"exif": exif.tobytes()}
    if xmp is not None:
        kwargs["xmp"] = xmp.encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path, "JPEG", **kwargs)
    return path


DJI_XMP = (
    '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
    '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" drone-dji:RelativeAltitude="+40.10"'
    ' drone-dji:GimbalYawDegree="-30.5" drone-dji:GimbalPitchDegree="-90.0" drone-dji:GimbalRollDegree="0.0">'
    "<drone-dji:RtkStdLat>0.02</drone-dji:RtkStdLat><drone-dji:RtkStdLon>0.03</drone-dji:RtkStdLon>"
    "<drone-dji:RtkStdHgt>0.05</drone-dji:RtkStdHgt></rdf:Description></rdf:RDF></x:xmpmeta>"
)


def test_exif_written_with_pil(tmp_path):
    path = write_gps_jpeg(tmp_path / "flat" / "IMG_1.JPG", -33.8688, 151.2093, 58.25, xmp=DJI_XMP)
    d = read_exif(path)
    assert (d.width, d.height) == (64, 48)
    assert d.lat == pytest.approx(-33.8688, abs=1e-7) and d.lon == pytest.approx(151.2093, abs=1e-7)
    assert d.alt == pytest.approx(58.25) and d.rel_alt == pytest.approx(40.1)
    assert d.gimbal_ypr == (-30.5, -90.0, 0.0) and d.rtk_std == (0.03, 0.02, 0.05)
    cam = camera_from_exif(d)
    assert cam.model == "SIMPLE_RADIAL" and cam.params[0] == pytest.approx(24 * 80 / 43.27)
    # a flat folder is the aerial set
    assert list(image_paths(tmp_path / "flat")) == ["aerial/IMG_1.JPG"]
    (rec,) = read_pos(tmp_path / "flat")
    assert rec.name == "aerial/IMG_1.JPG" and rec.h == pytest.approx(58.25)
    assert rec.rel_alt == pytest.approx(40.1) and rec.crs == "EPSG:4326"  # the take-off 18.15 m up
    assert (rec.std_xy, rec.std_z) == (0.03, 0.05)
    np.testing.assert_allclose(rec.R_world_from_cam, ypr_to_matrix(-30.5, -90, 0), atol=1e-12)
    (rel,) = read_pos_exif(tmp_path / "flat", altitude="relative", takeoff_h=100.0)
    assert rel.h == pytest.approx(140.1)


def test_exif_errors(tmp_path):
    d = tmp_path / "images" / "aerial"
    write_gps_jpeg(d / "ok.jpg", 55.7, 13.19, 80.0)
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(d / "nogps.jpg")
    data = (d / "ok.jpg").read_bytes()
    (d / "cut.jpg").write_bytes(data[: len(data) // 2])
    (d / "junk.jpg").write_bytes(b"not an image at all")
    with pytest.raises(ImageError, match="truncated JPEG"):
        check_image(d / "cut.jpg")
    with pytest.raises(ImageError, match="truncated JPEG"):
        check_image(d / "cut.jpg", decode=True)
    with pytest.raises(PosError) as e:
        read_pos(tmp_path / "images")
    msg = str(e.value)
    assert "image 'aerial/nogps.jpg': no GPS position in its EXIF" in msg
    assert "aerial/cut.jpg" in msg and "truncated JPEG" in msg
    assert "aerial/junk.jpg" in msg and "cannot read image" in msg
    assert len(e.value.errors) == 3


@needs_brighton
def test_exif_of_a_dji_image():
    d = read_exif(BRIGHTON / "DJI_0018.JPG")
    assert (d.width, d.height) == (4000, 2250) and d.make == "DJI"
    assert 46.8 < d.lat < 46.9 and -92.1 < d.lon < -91.9
    assert 150 < d.alt < 250 and 30 < d.rel_alt < 50
    assert d.gimbal_ypr[1] == pytest.approx(-89.9)
    cam = camera_from_exif(d)
    assert cam.params[0] == pytest.approx(20 * np.hypot(4000, 2250) / 43.27)


def test_focal_length_from_the_focal_plane_resolution(tmp_path):
    """No 35 mm equivalent: FocalLength (mm) and FocalPlaneXResolution give the focal length in pixels."""
    no35 = {0xA405: None, 0x920A: 8.8}  # a 1" sensor, 13.2 mm wide, 5472 px across
    res = {0xA20E: 5472 / 13.2, 0xA210: 4}  # pixels per mm
    d = read_exif(write_gps_jpeg(tmp_path / "a.jpg", 55.7, 13.19, 80.0, exif_tags={**no35, **res}))
    assert d.focal_35mm is None and d.focal_plane_px_per_mm == pytest.approx(5472 / 13.2)
    # the EXIF is that of the full 5472 px image, this copy is 64 px wide: the focal length scales
    full = {**no35, **res, 0xA002: 5472}
    cam = camera_from_exif(read_exif(write_gps_jpeg(tmp_path / "b.jpg", 55.7, 13.19, 80.0, exif_tags=full)))
    assert cam.params[0] == pytest.approx(8.8 / 13.2 * 64)
    assert camera_from_exif(d).params[0] == pytest.approx(8.8 * 5472 / 13.2)  # no PixelXDimension: as is
    inch = {**no35, 0xA20E: 5472 / 13.2 * 25.4, 0xA210: 2, 0xA002: 5472}  # pixels per inch
    cam = camera_from_exif(read_exif(write_gps_jpeg(tmp_path / "c.jpg", 55.7, 13.19, 80.0, exif_tags=inch)))
    assert cam.params[0] == pytest.approx(8.8 / 13.2 * 64)
    # the 35 mm equivalent wins; without either, no prior (as before)
    both = {**full, 0xA405: 24}
    cam = camera_from_exif(read_exif(write_gps_jpeg(tmp_path / "d.jpg", 55.7, 13.19, 80.0, exif_tags=both)))
    assert cam.params[0] == pytest.approx(24 * 80 / 43.27)
    for tags in (no35, {**no35, 0xA20E: 400.0, 0xA210: 1}, {0xA405: None, 0xA20E: 400.0, 0xA210: 4}):
        path = write_gps_jpeg(tmp_path / "e.jpg", 55.7, 13.19, 80.0, exif_tags=tags)
        assert camera_from_exif(read_exif(path)) is None  # no resolution, no unit, no focal length


# -- dispatch and images <-> POS ---------------------------------------------------------------
def test_read_pos_options_go_to_the_readers_that_take_them(tmp_path):
    recs = _recs()
    csv = write_pos_csv(tmp_path / "pos.csv", recs)
    js = write_pos_json(tmp_path / "p.json", recs)
    geo = tmp_path / "geo.txt"
    geo.write_text("EPSG:4326\naerial/A.jpg 13.19 55.70 80 90 30 0\n")
    options = {"pitch_zero": "horizon", "altitude": "relative", "takeoff_h": 10.0}
    for p in (csv, js):  # these readers take no option: none is passed (was a TypeError)
        assert [r.name for r in read_pos(p, **options)] == [r.name for r in recs]
    (a,) = read_pos(geo, **options)  # pitch_zero reaches the geo.txt reader
    np.testing.assert_allclose(a.R_world_from_cam, ypr_to_matrix(90, 30, 0), atol=1e-12)
    (b,) = read_pos(geo)  # auto: ODM's nadir-zero pitch
    np.testing.assert_allclose(b.R_world_from_cam, ypr_to_matrix(90, -60, 0), atol=1e-12)
    write_gps_jpeg(tmp_path / "flat" / "IMG_1.JPG", 55.7, 13.19, 58.25, xmp=DJI_XMP)
    (e,) = read_pos(tmp_path / "flat", **options)  # altitude and takeoff_h reach the EXIF reader
    assert e.h == pytest.approx(50.1)
    with pytest.raises(TypeError, match="unknown option.*pitch_zeor"):
        read_pos(csv, pitch_zeor="nadir")


def test_read_pos_dispatch_and_names(tmp_path):
    recs = _recs()
    names = [r.name for r in recs]
    csv = write_pos_csv(tmp_path / "pos.csv", recs)
    js = write_pos_json(tmp_path / "p.json", recs)
    geo = write_geo_txt(tmp_path / "geo.txt", recs, bare_names=True)  # ODM: bare file names
    other = tmp_path / "pos.dat"
    other.write_text(js.read_text())
    for p in (csv, js, geo, other):
        assert [r.name for r in read_pos(p, image_names=names)] == names
    with pytest.raises(PosError, match="image 'aerial/A0003.jpg' has no POS row"):
        read_pos(csv, image_names=[*names, "aerial/A0003.jpg"])
    with pytest.raises(PosError, match="POS row 'aerial/A0002.jpg' names no uploaded image"):
        read_pos(js, image_names=names[:1])
    with pytest.raises(PosError, match="no such file"):
        read_pos(tmp_path / "missing.csv")
