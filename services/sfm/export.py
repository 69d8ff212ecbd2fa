"""Camera outputs of a georeferenced reconstruction, in WGS84 and in the user's CRS.

- cameras.geojson: camera positions and footprints in WGS84 (RFC 7946), always.
- cameras.csv: the registered cameras in the output CRS, in the POS CSV format (docs/formats.md:
  `# crs:` directive, then name,x,y,z or name,lat,lon,h, with yaw,pitch,roll), so `read_pos` reads it
  back; attitudes are in the local ENU frame at each camera, like the POS.
- cameras.epsg<code>.geojson: positions and footprints in a projected output CRS (legacy `crs` member).

The output CRS is `out_crs`: "auto" is the POS input CRS unless that is WGS84 latitude/longitude (then
WGS84 only), None or "none" writes WGS84 only, any other value is a CRS code pyproj knows.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pycolmap

from services.pos import LocalFrame, PosRecord, is_wgs84_geographic, parse_crs, write_pos_csv

from .geojson import write_geojson

logger = logging.getLogger("midview.sfm.export")

default_conf: dict[str, Any] = {"out_crs": "auto", "footprints": True}


def resolve_crs(out_crs: str | None, pos_crs: str | None) -> str | None:
    """The output CRS of `out_crs` given the POS CRS (None: WGS84 only); CRSError if unknown."""
    if out_crs is None or str(out_crs).lower() == "none":
        return None
    if str(out_crs).lower() == "auto":
        return None if is_wgs84_geographic(pos_crs) else pos_crs
    parse_crs(out_crs)
    return str(out_crs)


def crs_tag(crs: str) -> str:
    """A file-name tag of a CRS: `epsg32633`, else a sanitised form of the code."""
    code = parse_crs(crs).to_epsg()
    return f"epsg{code}" if code else "".join(c if c.isalnum() else "_" for c in crs).strip("_").lower()


def camera_records(rec: pycolmap.Reconstruction, frame: LocalFrame) -> list[PosRecord]:
    """The registered cameras as PosRecords: WGS84 positions, attitudes in the ENU frame at each camera."""
    out = []
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        if not img.has_pose:
            continue
        lat, lon, h = (float(v[0]) for v in frame.to_wgs84(img.projection_center()[None]))
        R_frame = img.cam_from_world().rotation.matrix().T  # world (this frame) from camera
        R = frame.rotation_to_enu_at(lat, lon) @ R_frame
        out.append(PosRecord(img.name, lat, lon, h, R))
    return out


def main(
    conf: dict[str, Any],
    rec: pycolmap.Reconstruction,
    frame: LocalFrame,
    out_dir: str | Path,
    pos_crs: str | None = None,
    residuals: dict[str, float] | None = None,
    ground_z: float | None = None,
) -> Path:
    """Write cameras.geojson and, with an output CRS, cameras.csv and its GeoJSON; returns out_dir."""
    conf = {**default_conf, **(conf or {})}
    out_dir = Path(out_dir)
    write_geojson(out_dir / "cameras.geojson", rec, frame, residuals, ground_z)
    crs = resolve_crs(conf["out_crs"], pos_crs)
    for p in (out_dir / "cameras.csv", *out_dir.glob("cameras.epsg*.geojson")):
        p.unlink(missing_ok=True)  # outputs of an earlier run in another CRS
    if crs is None:
        return out_dir
    records = camera_records(rec, frame)
    if records:
        write_pos_csv(out_dir / "cameras.csv", records, crs=crs)
    if conf["footprints"] and parse_crs(crs).is_projected:
        write_geojson(out_dir / f"cameras.{crs_tag(crs)}.geojson", rec, frame, residuals, ground_z, crs)
    logger.info("camera positions in %s -> %s", crs, out_dir / "cameras.csv")
    return out_dir


def output_files(crs: str | None, footprints: bool = True) -> list[str]:
    """Names of the files `main` writes for an output CRS."""
    if crs is None:
        return ["cameras.geojson"]
    extra = [f"cameras.{crs_tag(crs)}.geojson"] if footprints and parse_crs(crs).is_projected else []
    return ["cameras.geojson", "cameras.csv", *extra]
