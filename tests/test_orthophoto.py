"""The orthophoto (services.views.orthophoto) of an analytic scene: a striped ground with a 12 m tall box
whose roof is red, rendered from straight above and put at each point's own latitude and longitude. The
roof must cover the box's footprint and nothing beside it (a perspective image from 1000 m would shift a
12 m roof by 0.5 m at 40 m from its centre; the orthophoto does not), and the GeoTIFF must carry the
bounds the map uses."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from services.colmap_model import Camera, Pose
from services.pos import LocalFrame
from services.views.orthophoto import Orthophoto, read_geotiff_bounds, render_orthophoto, write_geotiff

FRAME = LocalFrame(55.7, 13.19, 30.0)
BOX = (np.array([20.0, -10.0, 0.0]), np.array([40.0, 10.0, 12.0]))  # east of the centre
RED = np.array([220, 30, 30], np.uint8)


class BoxOnStripes:
    """Ray casts the ground z = 0 (grey stripes 2 m wide along east) and the box (red roof, blue walls)."""

    name = "analytic"

    def render(self, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        H, W = camera.height, camera.width
        v, u = np.mgrid[0:H, 0:W]
        rays = np.stack(
            [(u + 0.5 - camera.K[0, 2]) / camera.K[0, 0], (v + 0.5 - camera.K[1, 2]) / camera.K[1, 1]]
        )
        d = np.concatenate([rays, np.ones((1, H, W))]).reshape(3, -1).T @ pose.R  # world direction per z
        C = pose.center
        lo, hi = BOX
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - C) / d, (hi - C) / d
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            t_box = np.where((tmax >= tmin) & (tmin > 0), tmin, np.inf)
            t_ground = np.where(d[:, 2] < 0, -C[2] / d[:, 2], np.inf)
        t = np.minimum(t_box, t_ground)
        X = C + t[:, None] * d
        grey = np.where(np.floor(X[:, 0] / 2.0) % 2 == 0, 90, 170).astype(np.uint8)
        rgb = np.repeat(grey[:, None], 3, 1)
        roof = np.isfinite(t_box) & (t_box <= t_ground) & (np.abs(X[:, 2] - hi[2]) < 1e-6)
        wall = np.isfinite(t_box) & (t_box <= t_ground) & ~roof
        rgb[roof], rgb[wall] = RED, (30, 30, 220)
        depth = np.where(np.isfinite(t), t, 0.0)  # z-depth: the rays have unit z
        return rgb.reshape(H, W, 3), depth.reshape(H, W).astype(np.float32)


def _pixel(o: Orthophoto, east: float, north: float) -> np.ndarray:
    lat, lon, _ = FRAME.to_wgs84(np.array([[east, north, 0.0]]))
    s, w, n, e = o.bounds
    H, W = o.alpha.shape
    return o.rgb[int((n - lat[0]) / (n - s) * H), int((lon[0] - w) / (e - w) * W)]


@pytest.fixture(scope="module")
def ortho() -> Orthophoto:
    conf = {"max_size_px": 600, "altitude_m": 1000.0, "fill_px": 5}
    return render_orthophoto(BoxOnStripes(), FRAME, (-50.0, -40.0, 50.0, 40.0, 0.0), conf)


def test_the_roof_stands_over_its_footprint(ortho):
    assert ortho.alpha.mean() > 0.99
    assert (_pixel(ortho, 30.0, 0.0) == RED).all()
    for east in (20.3, 39.7):  # just inside the footprint's west and east edges
        assert (_pixel(ortho, east, 0.0) == RED).all(), east
    for east in (19.6, 40.4):  # just outside: the ground, not the roof shifted outwards
        assert not (_pixel(ortho, east, 0.0) == RED).all(), east
    stripes = [int(_pixel(ortho, x, -30.0)[0]) for x in (-9.0, -7.0, -5.0)]  # 2 m stripes on the ground
    assert stripes == [170, 90, 170]


def test_the_geotiff_carries_the_bounds_and_the_alpha(ortho, tmp_path):
    path = write_geotiff(tmp_path / "o.tif", ortho)
    assert read_geotiff_bounds(path) == pytest.approx(ortho.bounds, abs=1e-9)
    data = tifffile.imread(path)
    assert data.shape == (*ortho.alpha.shape, 4) and (data[..., :3] == ortho.rgb).all()
    assert ((data[..., 3] == 255) == ortho.alpha).all()
    with tifffile.TiffFile(path) as tif:
        keys = tif.pages[0].tags[34735].value
    assert tuple(keys[-4:]) == (2048, 0, 1, 4326)  # WGS84
