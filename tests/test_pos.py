"""POS CSV format, attitude conventions and coordinate frames."""

from __future__ import annotations

import numpy as np
import pytest

from services.pos import (
    LocalFrame,
    PosError,
    PosRecord,
    check_against_images,
    matrix_to_opk,
    matrix_to_ypr,
    opk_to_matrix,
    parse_pos_csv,
    read_pos_csv,
    write_pos_csv,
    ypr_to_matrix,
)


def test_ypr_known_cases():
    # yaw 0, pitch 0 looks north with the image x axis east
    R = ypr_to_matrix(0, 0, 0)
    np.testing.assert_allclose(R[:, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [1, 0, 0], atol=1e-12)
    # yaw 90 looks east; pitch -45 looks down at 45 degrees
    np.testing.assert_allclose(ypr_to_matrix(90, -45, 0)[:, 2], [np.sqrt(0.5), 0, -np.sqrt(0.5)], atol=1e-12)
    # nadir, yaw 0: the image top (-y) points north
    R = ypr_to_matrix(0, -90, 0)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(-R[:, 1], [0, 1, 0], atol=1e-12)
    # positive roll turns the image x axis downwards (clockwise as the camera sees it)
    assert ypr_to_matrix(0, 0, 10)[2, 0] < 0


def test_opk_known_cases():
    # omega = phi = kappa = 0 is the nadir camera with the image top north, same as yaw 0 pitch -90
    np.testing.assert_allclose(opk_to_matrix(0, 0, 0), ypr_to_matrix(0, -90, 0), atol=1e-12)
    # kappa 90 turns the nadir image: the image top then points west
    R = opk_to_matrix(0, 0, 90)
    np.testing.assert_allclose(-R[:, 1], [-1, 0, 0], atol=1e-12)
    # omega tilts the optical axis towards north (rotation about the east axis)
    assert opk_to_matrix(10, 0, 0)[1, 2] > 0


@pytest.mark.parametrize("ypr", [(0, 0, 0), (90, -45, 0), (200, -30, 5), (359, 10, -20), (45, -89, 3)])
def test_attitude_round_trips(ypr):
    R = ypr_to_matrix(*ypr)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(ypr_to_matrix(*matrix_to_ypr(R)), R, atol=1e-9)
    np.testing.assert_allclose(opk_to_matrix(*matrix_to_opk(R)), R, atol=1e-9)


def test_local_frame_round_trip_and_scale():
    f = LocalFrame(55.7047, 13.1910, 70.0)
    enu = f.from_wgs84([55.7047 + 1e-3], [13.1910], [70.0])
    assert enu[0, 1] == pytest.approx(111.3, abs=0.5)  # 0.001 deg of latitude ~ 111 m north
    lat, lon, h = f.to_wgs84(np.array([[100.0, -50.0, 12.0]]))
    np.testing.assert_allclose(f.from_wgs84(lat, lon, h), [[100.0, -50.0, 12.0]], atol=1e-6)


def _records() -> list[PosRecord]:
    return [
        PosRecord("aerial/A0001.jpg", 55.7047, 13.1910, 130.5, ypr_to_matrix(90, -45, 0), 0.5, 1.0, 1.5),
        PosRecord("ground/G0001.jpg", 55.7049, 13.1913, 71.8, ypr_to_matrix(181, 2, -1), 3.0, 5.0, 2.0),
        PosRecord("ground/G0002.jpg", 55.7050, 13.1914, 71.7, None),
    ]


@pytest.mark.parametrize(("crs", "attitude"), [("EPSG:4979", "ypr"), ("EPSG:32633", "opk")])
def test_pos_csv_round_trip(tmp_path, crs, attitude):
    recs = _records()
    path = write_pos_csv(tmp_path / "pos.csv", recs, crs=crs, attitude=attitude)
    back = read_pos_csv(path)
    assert [r.name for r in back] == [r.name for r in recs]
    f = LocalFrame(55.7047, 13.1910, 70.0)
    for a, b in zip(recs, back, strict=True):
        np.testing.assert_allclose(
            f.from_wgs84(b.lat, b.lon, b.h), f.from_wgs84(a.lat, a.lon, a.h), atol=1e-3
        )
        if a.R_world_from_cam is None:
            assert b.R_world_from_cam is None
        else:
            np.testing.assert_allclose(b.R_world_from_cam, a.R_world_from_cam, atol=1e-6)
        assert (b.std_xy, b.std_z, b.std_att) == (a.std_xy, a.std_z, a.std_att)


HEADER = "name,lat,lon,h,yaw,pitch,roll\n"


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ("aerial/a.jpg,55.7,13.1,abc,0,0,0\n", "line 2, column h: 'abc' is not a number"),
        ("aerial/a.jpg,95.0,13.1,50,0,0,0\n", "column lat: 95.0 is outside"),
        ("aerial/a.jpg,55.7,13.1,nan,0,0,0\n", "column h: 'nan' is not finite"),
        ("aerial/a.jpg,55.7,13.1,50,0,0\n", "6 fields, the header has 7"),
        (
            "aerial/a.jpg,55.7,13.1,50,0,0,0\naerial/a.jpg,55.7,13.1,50,0,0,0\n",
            "duplicate name 'aerial/a.jpg'",
        ),
        (",55.7,13.1,50,0,0,0\n", "empty image name"),
        ("aerial/a.jpg,55.7,13.1,50,999,0,0\n", "column yaw: 999.0 is outside"),
    ],
)
def test_bad_rows_are_named(rows, message):
    with pytest.raises(PosError) as e:
        parse_pos_csv(HEADER + rows, source="pos.csv")
    assert message in str(e.value)


def test_every_bad_row_is_reported():
    text = HEADER + "a/1.jpg,55.7,13.1,x,0,0,0\na/2.jpg,55.7,13.1,50,0,0,0\na/3.jpg,91,13.1,50,0,0,0\n"
    with pytest.raises(PosError) as e:
        parse_pos_csv(text)
    assert len(e.value.errors) == 2


def test_unknown_crs_and_missing_columns():
    with pytest.raises(PosError, match="unknown CRS"):
        parse_pos_csv("# crs: EPSG:999999\n" + HEADER)
    with pytest.raises(PosError, match="header lacks x, y, z"):
        parse_pos_csv("# crs: EPSG:32633\n" + HEADER + "a/1.jpg,55.7,13.1,50,0,0,0\n")


def test_pos_against_images():
    recs = _records()
    check_against_images(recs, [r.name for r in recs])
    with pytest.raises(PosError) as e:
        check_against_images(recs[:2], ["aerial/A0001.jpg", "ground/G0001.jpg", "ground/G0009.jpg"])
    assert "image 'ground/G0009.jpg' has no POS row" in str(e.value)
    with pytest.raises(PosError, match="names no uploaded image"):
        check_against_images(recs, ["aerial/A0001.jpg", "ground/G0001.jpg"])
