"""An orthophoto of the survey from its aerial images, for the map and for GIS users.

A nadir view from high above the site (`altitude_m`) is rendered with the views' renderer (coloured from
the full-resolution aerial images through the plane proxy, as the intermediate views are); each pixel's
3D point is then put at its own latitude and longitude, so that roofs stand over their footprints (true
ortho, not the perspective of one camera); cells no point lands in (walls hidden from straight above)
are filled from their neighbours. Written as a GeoTIFF in WGS84 (EPSG:4326, the RGB bands and an alpha
band) and as a PNG with its bounds (orthophoto.json) for the dashboard's map.

    path = orthophoto.main(conf, renderer, "sfm/sparse", "sfm/georef.json", "views")

Shapes: rgb (H, W, 3) uint8, alpha (H, W) bool; bounds (south, west, north, east) in degrees.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pycolmap

from services.colmap_model import Camera
from services.geometry import look_at
from services.pos import LocalFrame
from services.sfm import read_georef_frame

if TYPE_CHECKING:
    from services.views.rendering import Renderer

logger = logging.getLogger("midview.views.orthophoto")

confs: dict[str, dict[str, Any]] = {
    "default": {
        "enabled": True,
        "max_size_px": 1536,  # the longer side of the rendered nadir view and of the orthophoto
        "altitude_m": 1000.0,  # the nadir view's height above the site (within the renderer's max depth)
        "extent_quantile": 0.02,  # the site: these quantiles of the sparse points' east and north
        "margin_m": 5.0,
        "fill_px": 5,  # holes up to about this many cells wide are filled from their neighbours
    },
}
TIFF, PNG, BOUNDS = "orthophoto.tif", "orthophoto.png", "orthophoto.json"


@dataclass
class Orthophoto:
    rgb: np.ndarray  # (H, W, 3) uint8, north up
    alpha: np.ndarray  # (H, W) bool: covered
    bounds: tuple[float, float, float, float]  # south, west, north, east (degrees)

    @property
    def pixel_deg(self) -> tuple[float, float]:
        """(longitude, latitude) size of a cell in degrees."""
        s, w, n, e = self.bounds
        H, W = self.alpha.shape
        return (e - w) / W, (n - s) / H


def site_extent(points: np.ndarray, conf: dict) -> tuple[float, float, float, float, float]:
    """(x0, y0, x1, y1, ground z) of points (N, 3) in the local frame: the quantiles of their east and
    north with the margin; the ground their low height quantile."""
    q, m = float(conf["extent_quantile"]), float(conf["margin_m"])
    lo, hi = np.quantile(points[:, :2], q, axis=0) - m, np.quantile(points[:, :2], 1 - q, axis=0) + m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), float(np.quantile(points[:, 2], q))


def render_orthophoto(
    renderer: Renderer, frame: LocalFrame, extent: tuple[float, float, float, float, float], conf: dict
) -> Orthophoto:
    """The orthophoto of the site `extent` (site_extent) through `renderer`, in the frame `frame`."""
    x0, y0, x1, y1, z0 = extent
    size = int(conf["max_size_px"])
    span = max(x1 - x0, y1 - y0)
    W, H = (
        (size, max(1, round(size * (y1 - y0) / span)))
        if x1 - x0 >= y1 - y0
        else (
            max(1, round(size * (x1 - x0) / span)),
            size,
        )
    )
    alt = float(conf["altitude_m"])
    f = alt * W / (x1 - x0)
    camera = Camera("PINHOLE", W, H, [f, f, W / 2, H / 2])
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, z0])
    pose = look_at(centre + [0.0, 0.0, alt], centre)  # straight down, image top north
    rgb, depth = renderer.render(camera, pose)
    v, u = np.nonzero(depth > 0)
    X = pose.unproject(camera.K, np.stack([u + 0.5, v + 0.5], 1), depth[v, u].astype(np.float64))
    corners = np.array([[x0, y0, z0], [x1, y1, z0], [x0, y1, z0], [x1, y0, z0]])
    clat, clon, _ = frame.to_wgs84(corners)
    south, north, west, east = float(clat.min()), float(clat.max()), float(clon.min()), float(clon.max())
    lat, lon, _ = frame.to_wgs84(X)
    col = np.floor((lon - west) / (east - west) * W).astype(int)
    row = np.floor((north - lat) / (north - south) * H).astype(int)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    # the highest point of each cell wins (a roof over the street seen past its edge)
    order = np.argsort(X[inside, 2])
    r_, c_ = row[inside][order], col[inside][order]
    ortho = np.zeros((H, W, 3), np.uint8)
    ortho[r_, c_] = rgb[v[inside][order], u[inside][order]]
    covered = np.zeros((H, W), bool)
    covered[r_, c_] = True
    return _filled(Orthophoto(ortho, covered, (south, west, north, east)), int(conf["fill_px"]))


def _filled(o: Orthophoto, fill_px: int) -> Orthophoto:
    """Small holes (within the closing of the covered cells by fill_px) filled from their neighbours."""
    k = np.ones((2 * fill_px + 1, 2 * fill_px + 1), np.uint8)
    closed = cv2.morphologyEx(o.alpha.astype(np.uint8), cv2.MORPH_CLOSE, k).astype(bool)
    holes = closed & ~o.alpha
    if not holes.any():
        return o
    bgr = cv2.inpaint(o.rgb[..., ::-1].copy(), holes.astype(np.uint8), fill_px, cv2.INPAINT_TELEA)
    return Orthophoto(np.ascontiguousarray(bgr[..., ::-1]), closed, o.bounds)


def write_geotiff(path: str | Path, o: Orthophoto) -> Path:
    """A GeoTIFF in WGS84 (EPSG:4326): RGB and alpha bands, north up, the tie point at the north-west
    corner of the first cell (PixelIsArea)."""
    import tifffile

    s, w, n, e = o.bounds
    dlon, dlat = o.pixel_deg
    geokeys = [1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326]  # geographic, area, EPSG:4326
    rgba = np.dstack([o.rgb, np.where(o.alpha, 255, 0).astype(np.uint8)])
    tifffile.imwrite(
        path,
        rgba,
        photometric="rgb",
        extrasamples=["unassalpha"],
        compression="deflate",
        extratags=[
            (33550, "d", 3, (dlon, dlat, 0.0), True),  # ModelPixelScale
            (33922, "d", 6, (0.0, 0.0, 0.0, w, n, 0.0), True),  # ModelTiepoint
            (34735, "H", len(geokeys), geokeys, True),  # GeoKeyDirectory
        ],
    )
    return Path(path)


def read_geotiff_bounds(path: str | Path) -> tuple[float, float, float, float]:
    """(south, west, north, east) of a GeoTIFF written by write_geotiff, from its tags."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        sx, sy, _ = page.tags[33550].value
        _, _, _, w, n, _ = page.tags[33922].value
        H, W = page.shape[:2]
    return n - sy * H, w, n, w + sx * W


def main(
    conf: dict, renderer: Renderer, sparse: str | Path, georef: str | Path, out_dir: str | Path
) -> Path | None:
    """Write orthophoto.tif, orthophoto.png and orthophoto.json (bounds, size) to out_dir; returns the
    GeoTIFF's path, or None when disabled or the model has too few points to span a site."""
    c = {**confs["default"], **(conf or {})}
    if not c["enabled"]:
        return None
    rec = pycolmap.Reconstruction(str(sparse))
    points = np.array([p.xyz for p in rec.points3D.values()], float).reshape(-1, 3)
    if len(points) < 20:
        logger.warning("orthophoto: %d sparse points do not span a site; none written", len(points))
        return None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    o = render_orthophoto(renderer, read_georef_frame(georef), site_extent(points, c), c)
    tif = write_geotiff(out / TIFF, o)
    cv2.imwrite(str(out / PNG), np.dstack([o.rgb[..., ::-1], np.where(o.alpha, 255, 0).astype(np.uint8)]))
    s, w, n, e = o.bounds
    doc = {"bounds": {"south": s, "west": w, "north": n, "east": e}, "size": list(o.alpha.shape[::-1])}
    doc["covered"] = float(o.alpha.mean())
    (out / BOUNDS).write_text(json.dumps(doc, indent=1))
    logger.info("orthophoto %dx%d (%.0f%% covered) -> %s", *o.alpha.shape[::-1], 100 * doc["covered"], tif)
    return tif
