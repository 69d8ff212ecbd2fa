"""GIS outputs of a georeferenced reconstruction, for the tools mapping teams use.

- cameras.gpkg (layer `cameras`, Point Z in the output CRS) and cameras.geojson (WGS84, RFC 7946): every
  camera of the model, and the ground images it left out at their POS position, with the attributes a GIS
  user filters by: name, set, registered, registered_by, position_std_m, to_pos_m (distance to its
  POS), heading/pitch/roll (degrees, local ENU), reason (why an image did not register) and
  its named cause (services.sfm.combined.report.CAUSES).
- cameras_opk.txt: the registered cameras' exterior orientation, `name x y z omega phi kappa` in the
  output CRS (degrees; camera-to-map rotation Rx(omega) Ry(phi) Rz(kappa) of the photogrammetric
  camera axes: x right, y up, z back, as PATB, Pix4D and Metashape import it), the map axes those of
  the projected CRS (grid north: the meridian convergence is applied).
- points.las: the model's 3D points with their colours (LAS 1.4, point format 7), the CRS as WKT.

The output CRS must be projected (metres); with a geographic one (or none) the UTM zone of the site.
Heights are ellipsoidal, as the POS's.
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from pyproj import CRS, Proj, Transformer

from services.pos import LocalFrame, PosRecord, matrix_to_opk, matrix_to_ypr

logger = logging.getLogger("midview.sfm.gis")

FIELDS = (
    ("name", str),
    ("set", str),
    ("registered", bool),
    ("registered_by", str),
    ("position_std_m", float),
    ("to_pos_m", float),
    ("heading", float),
    ("pitch", float),
    ("roll", float),
    ("reason", str),
    ("cause", str),
)


def output_crs(crs: str | None, lat: float, lon: float) -> CRS:
    """The projected CRS of the outputs: `crs` when projected, else the UTM zone of (lat, lon)."""
    if crs:
        c = CRS.from_user_input(crs)
        if c.is_projected:
            return c
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def camera_rows(
    rec: pycolmap.Reconstruction, frame: LocalFrame, records: dict[str, PosRecord], report: dict
) -> list[dict]:
    """One row per camera: WGS84 position, R_world_from_cam in the ENU at the camera, attributes."""
    ground = report.get("ground", {}) if report else {}
    rows = []
    seen = set()
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        if not img.has_pose:
            continue
        c = np.asarray(img.projection_center())
        lat, lon, h = (float(v[0]) for v in frame.to_wgs84(c[None]))
        R = frame.rotation_to_enu_at(lat, lon) @ img.cam_from_world().rotation.matrix().T
        r = records.get(img.name)
        g = ground.get(img.name, {})
        rows.append(
            {
                "name": img.name,
                "set": img.name.split("/", 1)[0],
                "registered": True,
                "registered_by": g.get("registered_by")
                or ("aerial_sfm" if img.name.startswith("aerial/") else "mapper"),
                "position_std_m": g.get("position_std_m"),
                "to_pos_m": float(np.linalg.norm(c - frame.from_wgs84(r.lat, r.lon, r.h)[0])) if r else None,
                "lat": lat,
                "lon": lon,
                "h": h,
                "R": R,
                "reason": None,
                "cause": None,
            }
        )
        seen.add(img.name)
    for name, g in sorted(ground.items()):
        r = records.get(name)
        if name in seen or r is None:
            continue
        rows.append(
            {
                "name": name,
                "set": "ground",
                "registered": False,
                "registered_by": None,
                "position_std_m": None,
                "to_pos_m": None,
                "lat": r.lat,
                "lon": r.lon,
                "h": r.h,
                "R": None,
                "reason": g.get("reason"),
                "cause": g.get("cause"),
            }
        )
    for row in rows:
        ypr = matrix_to_ypr(row["R"]) if row["R"] is not None else (None, None, None)
        row["heading"], row["pitch"], row["roll"] = ypr
    return rows


def _wkb_point_z(x: float, y: float, z: float) -> bytes:
    return struct.pack("<BIddd", 1, 1001, x, y, z)


def write_gpkg(path: Path, rows: list[dict], crs: CRS, xyz: np.ndarray) -> Path:
    """The cameras layer as a GeoPackage (GDAL through pyogrio)."""
    from pyogrio.raw import write

    fields = [k for k, _ in FIELDS]

    def column(key: str, kind: type) -> np.ndarray:
        values = [r[key] for r in rows]
        if kind is bool:
            return np.array(values, dtype=bool)
        if kind is float:
            return np.array([np.nan if v is None else v for v in values], dtype=float)
        return np.array(values, dtype=object)

    data = [column(k, kind) for k, kind in FIELDS]
    geometry = np.array([_wkb_point_z(*p) for p in xyz], dtype=object)
    path.unlink(missing_ok=True)
    write(
        str(path), geometry, data, fields, driver="GPKG", layer="cameras", geometry_type="Point Z",
        crs=crs.to_wkt(),
    )  # fmt: skip
    return path


def write_geojson(path: Path, rows: list[dict]) -> Path:
    """The cameras as GeoJSON (RFC 7946: longitude, latitude, ellipsoidal height)."""
    feats = [
        {
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [r["lon"], r["lat"], r["h"]]},
            "properties": {k: r[k] for k, _ in FIELDS},
        }
        for r in rows
    ]
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}, indent=1))
    return path


def write_opk(path: Path, rows: list[dict], crs: CRS, xyz: np.ndarray) -> Path:
    """Exterior orientation of the registered cameras: name x y z omega phi kappa (see module doc)."""
    proj = Proj(crs)
    lines = [
        f"# midview exterior orientation; CRS {crs.to_string()} ({crs.name}), ellipsoidal heights",
        "# camera-to-map rotation Rx(omega) Ry(phi) Rz(kappa), camera axes x right, y up, z back; degrees",
        "# name x y z omega phi kappa",
    ]
    for r, (x, y, z) in zip(rows, xyz, strict=True):
        if r["R"] is None:
            continue
        gamma = np.radians(proj.get_factors(r["lon"], r["lat"]).meridian_convergence)
        c, s = np.cos(gamma), np.sin(gamma)
        grid_from_enu = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        o, p, k = matrix_to_opk(grid_from_enu @ r["R"])
        lines.append(f"{r['name']} {x:.4f} {y:.4f} {z:.4f} {o:.6f} {p:.6f} {k:.6f}")
    path.write_text("\n".join(lines) + "\n")
    return path


def write_las(path: Path, rec: pycolmap.Reconstruction, frame: LocalFrame, crs: CRS) -> Path:
    """The model's 3D points and colours as LAS 1.4 (point format 7), coordinates in `crs`."""
    import laspy

    pts = sorted(rec.points3D.items())
    xyz_enu = np.array([p.xyz for _, p in pts], float).reshape(-1, 3)
    rgb = np.array([p.color for _, p in pts], np.uint16).reshape(-1, 3)
    x, y, z = to_crs(frame, xyz_enu, crs)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array(
        [np.floor(x.min()) if len(x) else 0.0, np.floor(y.min()) if len(y) else 0.0, 0.0]
    )
    header.add_crs(crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z
    las.red, las.green, las.blue = (rgb[:, i] * 257 for i in range(3))
    las.write(str(path))
    return path


def to_crs(frame: LocalFrame, enu: np.ndarray, crs: CRS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local ENU points -> (x, y, ellipsoidal h) in a projected CRS."""
    lat, lon, h = frame.to_wgs84(np.asarray(enu, float).reshape(-1, 3))
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    return np.asarray(x, float), np.asarray(y, float), np.asarray(h, float)


def main(
    rec: pycolmap.Reconstruction,
    frame: LocalFrame,
    records: dict[str, PosRecord],
    report: dict,
    out_dir: str | Path,
    crs: str | None = None,
) -> dict[str, Any]:
    """Write the GIS outputs into out_dir; returns {"crs": code, "files": [...]}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = camera_rows(rec, frame, records, report)
    lat0, lon0, _ = (float(v[0]) for v in frame.to_wgs84(np.zeros((1, 3))))
    ocrs = output_crs(crs, lat0, lon0)
    proj = Transformer.from_crs("EPSG:4326", ocrs, always_xy=True)
    xs, ys = proj.transform([r["lon"] for r in rows], [r["lat"] for r in rows])
    xyz = np.c_[np.asarray(xs, float), np.asarray(ys, float), [r["h"] for r in rows]].reshape(-1, 3)
    files = [
        write_gpkg(out / "cameras.gpkg", rows, ocrs, xyz),
        write_geojson(out / "cameras.geojson", rows),
        write_opk(out / "cameras_opk.txt", rows, ocrs, xyz),
        write_las(out / "points.las", rec, frame, ocrs),
    ]
    code = ocrs.to_epsg()
    logger.info("GIS outputs in EPSG:%s: %s", code, ", ".join(p.name for p in files))
    return {"crs": f"EPSG:{code}" if code else ocrs.to_wkt(), "files": [p.name for p in files]}
