"""Camera positions and image footprints of a georeferenced reconstruction as GeoJSON: WGS84
(RFC 7946) by default, or the coordinates of another CRS with the legacy `crs` member that GIS tools
read (`urn:ogc:def:crs:EPSG::<code>`), easting (or longitude) first.

Footprints intersect the rays through the four image corners with a horizontal ground plane (by
default the median height of the 3D points). Corners whose ray does not reach the plane in front of
the camera (oblique views above the horizon) leave the image without a footprint.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap

from services.pos import LocalFrame, from_wgs84, parse_crs


def ground_height(rec: pycolmap.Reconstruction) -> float | None:
    """Median height (ENU up) of the reconstruction's 3D points, None without points."""
    if rec.num_points3D() == 0:
        return None
    return float(np.median([p.xyz[2] for p in rec.points3D.values()]))


def footprint(img: pycolmap.Image, ground_z: float, max_range: float = 1e4) -> np.ndarray | None:
    """(4, 3) ENU corners of the image on the plane z = ground_z, None if a corner misses it."""
    cam = img.camera
    w, h = cam.width, cam.height
    corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    rays = np.concatenate([cam.cam_from_img(corners), np.ones((4, 1))], 1)
    R_wc = img.cam_from_world().rotation.matrix().T
    d = rays @ R_wc.T
    c = img.projection_center()
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (ground_z - c[2]) / d[:, 2]
    if (
        not np.all(np.isfinite(lam))
        or np.any(lam <= 0)
        or np.any(lam * np.linalg.norm(d, axis=1) > max_range)
    ):
        return None
    return c + lam[:, None] * d


def coordinates(frame: LocalFrame, enu: np.ndarray, crs: str | None = None) -> np.ndarray:
    """(N, 3) GeoJSON positions of ENU points: [lon, lat, h] (WGS84) or [x, y, z] in `crs`."""
    lat, lon, h = frame.to_wgs84(np.atleast_2d(enu))
    if crs is None:
        return np.stack([lon, lat, h], -1)
    a, b, c = from_wgs84(crs, lat, lon, h)
    if parse_crs(crs).is_geographic:  # from_wgs84 gives (lat, lon, h) there
        a, b = b, a
    out = np.stack([a, b, c], -1)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{crs}: the camera positions do not transform into it (a missing grid?)")
    return out


def _ring(frame: LocalFrame, enu: np.ndarray, crs: str | None = None) -> list[list[float]]:
    """Closed, counter-clockwise (RFC 7946) [lon, lat] (or [x, y] in `crs`) ring of ENU points."""
    x, y = enu[:, 0], enu[:, 1]
    if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:  # clockwise: reverse
        enu = enu[::-1]
    ring = [[float(a), float(b)] for a, b, _ in coordinates(frame, enu, crs)]
    return ring + ring[:1]


def camera_features(
    rec: pycolmap.Reconstruction,
    frame: LocalFrame,
    residuals: dict[str, float] | None = None,
    ground_z: float | None = None,
    crs: str | None = None,
) -> dict:
    """A FeatureCollection: per registered image a Point (camera centre) and, if it hits the ground, a
    Polygon (footprint); properties name, set, kind, residual (georeferencing, metres). Coordinates in
    WGS84, or in `crs` (then with a `crs` member)."""
    residuals = residuals or {}
    z = ground_height(rec) if ground_z is None else ground_z
    feats = []
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        if not img.has_pose:
            continue
        props = {
            "name": img.name,
            "set": img.name.split("/", 1)[0] if "/" in img.name else "",
            "residual": residuals.get(img.name),
        }
        point = {
            "type": "Point",
            "coordinates": [float(v) for v in coordinates(frame, img.projection_center(), crs)[0]],
        }
        feats.append({"type": "Feature", "geometry": point, "properties": {**props, "kind": "camera"}})
        fp = None if z is None else footprint(img, z)
        if fp is not None:
            poly = {"type": "Polygon", "coordinates": [_ring(frame, fp, crs)]}
            feats.append(
                {
                    "type": "Feature",
                    "geometry": poly,
                    "properties": {**props, "kind": "footprint", "ground_z_enu": z},
                }
            )
    doc: dict = {"type": "FeatureCollection", "features": feats}
    if crs is not None:
        code = parse_crs(crs).to_epsg()
        name = f"urn:ogc:def:crs:EPSG::{code}" if code else parse_crs(crs).to_string()
        doc["crs"] = {"type": "name", "properties": {"name": name}}
    return doc


def write_geojson(
    path: str | Path,
    rec: pycolmap.Reconstruction,
    frame: LocalFrame,
    residuals: dict[str, float] | None = None,
    ground_z: float | None = None,
    crs: str | None = None,
) -> Path:
    """Write `camera_features` to a .geojson file."""
    path = Path(path)
    path.write_text(json.dumps(camera_features(rec, frame, residuals, ground_z, crs)))
    return path
