"""POS read from the stored images' EXIF GPS and DJI XMP (POST /projects/{id}/pos/from-exif), on both API
backends: real JPEGs written with PIL, and real DJI images from ../shared/data when present."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
from test_pos_formats import BRIGHTON, DJI_XMP, write_gps_jpeg

from services.pos import ypr_to_matrix


def _project(env, tenant) -> str:
    r = env.client.post("/projects", json={"name": f"p-{uuid.uuid4().hex[:8]}"}, headers=tenant.headers)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _upload(env, tenant, pid: str, files: dict[str, bytes], image_set: str = "aerial") -> None:
    parts = [("files", (name, data, "image/jpeg")) for name, data in files.items()]
    r = env.client.post(
        f"/projects/{pid}/images", params={"set": image_set}, files=parts, headers=tenant.headers
    )
    assert r.status_code == 201, r.text


def _gps_jpeg(tmp_path: Path, name: str, lat: float, lon: float, alt: float, xmp: str | None = None) -> bytes:
    return write_gps_jpeg(tmp_path / name, lat, lon, alt, xmp=xmp).read_bytes()


def test_pos_from_exif_stores_rows_or_nothing(api_env, make_jpeg, tmp_path: Path) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    _upload(api_env, t, pid, {
        "DJI_1.JPG": _gps_jpeg(tmp_path, "DJI_1.JPG", 55.7101, 13.1901, 120.5, xmp=DJI_XMP),
        "GPS_2.JPG": _gps_jpeg(tmp_path, "GPS_2.JPG", -33.8688, 151.2093, 58.25),
    })  # fmt: skip
    _upload(api_env, t, pid, {"G1.jpg": make_jpeg(seed=1)}, "ground")  # no EXIF at all
    url = f"/projects/{pid}/pos/from-exif"

    def rows() -> dict[str, dict]:
        return {r["image_name"]: r for r in c.get(f"/projects/{pid}/pos", headers=t.headers).json()}

    # every image by default: the ground photo has no GPS, so nothing is stored
    r = c.post(url, json={}, headers=t.headers)
    assert r.status_code == 422, r.text
    assert r.json()["detail"]["errors"] == ["image 'ground/G1.jpg': no GPS position in its EXIF"]
    assert "nothing stored" in r.json()["detail"]["message"] and rows() == {}

    # the aerial set, absolute (GPS) altitude, gimbal attitude from the XMP
    r = c.post(url, json={"image_set": "aerial"}, headers=t.headers)
    assert r.status_code == 200, r.text
    assert r.json() == {"format": "exif", "stored": 2, "total": 2, "removed": 0, "warnings": []}
    got = rows()
    dji, gps = got["aerial/DJI_1.JPG"], got["aerial/GPS_2.JPG"]
    assert dji["lat"] == pytest.approx(55.7101, abs=1e-7) and dji["lon"] == pytest.approx(13.1901, abs=1e-7)
    assert dji["h"] == pytest.approx(120.5) and dji["source_format"] == "exif"
    np.testing.assert_allclose(dji["attitude"], ypr_to_matrix(-30.5, -90.0, 0.0), atol=1e-9)
    assert (dji["std_xy"], dji["std_z"]) == (0.03, 0.05)  # RTK accuracies of the XMP
    assert gps["lat"] == pytest.approx(-33.8688, abs=1e-7) and gps["h"] == pytest.approx(58.25)
    assert gps["attitude"] is None

    # relative altitude: the image without XMP has none; the request fails whole, rows unchanged
    before = rows()
    r = c.post(url, json={"image_set": "aerial", "altitude": "relative", "takeoff_h": 10}, headers=t.headers)
    assert r.status_code == 422
    assert r.json()["detail"]["errors"] == [
        "image 'aerial/GPS_2.JPG': no XMP RelativeAltitude in its metadata"
    ]
    assert rows() == before
    # ... unless such images are skipped; attitude none drops the gimbal attitude
    body = {"altitude": "relative", "takeoff_h": 10, "attitude": "none", "skip_without_gps": True}
    r = c.post(url, json=body, headers=t.headers)
    assert r.status_code == 200, r.text
    assert r.json()["stored"] == 1 and len(r.json()["warnings"]) == 2  # GPS_2 and the ground photo
    assert (
        rows()["aerial/DJI_1.JPG"]["h"] == pytest.approx(50.1)
        and rows()["aerial/DJI_1.JPG"]["attitude"] is None
    )
    assert rows()["aerial/GPS_2.JPG"] == before["aerial/GPS_2.JPG"]

    # named images; unknown names, bad options and an unreadable stored object are 4xx, nothing stored
    before = rows()
    r = c.post(url, json={"names": ["aerial/GPS_2.JPG", "aerial/NOPE.jpg"]}, headers=t.headers)
    assert r.status_code == 422 and "aerial/NOPE.jpg" in r.json()["detail"]["errors"][0]
    assert c.post(url, json={"altitude": "ellipsoid"}, headers=t.headers).status_code == 422
    assert c.post(url, json={"image_set": "sky"}, headers=t.headers).status_code == 422
    from shared.storage.keys import image_key_for_name

    api_env.storage.delete(image_key_for_name(t.id, pid, "aerial/GPS_2.JPG"))
    r = c.post(url, json={"names": ["aerial/DJI_1.JPG", "aerial/GPS_2.JPG"]}, headers=t.headers)
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]["errors"]
    assert err.startswith("image 'aerial/GPS_2.JPG'") and str(tmp_path) not in err
    assert rows() == before
    other = api_env.tenant()
    assert c.post(url, json={}, headers=other.headers).status_code == 404


@pytest.mark.skipif(not BRIGHTON.is_dir(), reason=f"shared data absent: {BRIGHTON}")
def test_pos_from_exif_of_real_dji_images(api_env) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    names = ["DJI_0018.JPG", "DJI_0019.JPG"]
    _upload(api_env, t, pid, {n: (BRIGHTON / n).read_bytes() for n in names})
    r = c.post(
        f"/projects/{pid}/pos/from-exif", json={"altitude": "relative", "takeoff_h": 180}, headers=t.headers
    )
    assert r.status_code == 200, r.text
    assert r.json()["stored"] == 2
    rows = c.get(f"/projects/{pid}/pos", headers=t.headers).json()
    assert [row["image_name"] for row in rows] == [f"aerial/{n}" for n in names]
    for row in rows:
        assert 46.8 < row["lat"] < 46.9 and -92.1 < row["lon"] < -91.9
        assert 210 < row["h"] < 230 and row["attitude"] is not None  # 30..50 m above the take-off point
