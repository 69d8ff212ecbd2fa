"""Camera positions and image footprints of a georeferenced reconstruction as GeoJSON (WGS84).

Footprints intersect the rays through the four image corners with a horizontal ground plane (by
default the median height of the 3D points). Corners whose ray does not reach the plane in front of
the camera (oblique views above the horizon) leave the image without a footprint.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap

from services.pos import LocalFrame


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


def _ring(frame: LocalFrame, enu: np.ndarray) -> list[list[float]]:
    """Closed, counter-clockwise (RFC 7946) [lon, lat] ring of ENU points."""
    x, y = enu[:, 0], enu[:, 1]
    if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:  # clockwise: reverse
        enu = enu[::-1]
    lat, lon, _ = frame.to_wgs84(enu)
    ring = [[float(a), float(b)] for a, b in zip(lon, lat, strict=True)]
    return ring + ring[:1]


def camera_features(
    rec: pycolmap.Reconstruction,
    frame: LocalFrame,
    residuals: dict[str, float] | None = None,
    ground_z: float | None = None,
) -> dict:
    """A FeatureCollection: per registered image a Point (camera centre) and, if it hits the ground, a
    Polygon (footprint); properties name, set, kind, residual (georeferencing, metres)."""
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
        lat, lon, h = frame.to_wgs84(img.projection_center()[None])
        point = {"type": "Point", "coordinates": [float(lon[0]), float(lat[0]), float(h[0])]}
        feats.append({"type": "Feature", "geometry": point, "properties": {**props, "kind": "camera"}})
        fp = None if z is None else footprint(img, z)
        if fp is not None:
            poly = {"type": "Polygon", "coordinates": [_ring(frame, fp)]}
            feats.append(
                {
                    "type": "Feature",
                    "geometry": poly,
                    "properties": {**props, "kind": "footprint", "ground_z_enu": z},
                }
            )
    return {"type": "FeatureCollection", "features": feats}


def write_geojson(
    path: str | Path,
    rec: pycolmap.Reconstruction,
    frame: LocalFrame,
    residuals: dict[str, float] | None = None,
    ground_z: float | None = None,
) -> Path:
    """Write `camera_features` to a .geojson file."""
    path = Path(path)
    path.write_text(json.dumps(camera_features(rec, frame, residuals, ground_z)))
    return path
