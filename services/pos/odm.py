"""OpenDroneMap's image geolocation file (geo.txt).

```
EPSG:4326
DJI_0028.JPG -91.9942096111111 46.84252125 198.609 [yaw pitch roll] [horz_acc vert_acc] [extras...]
```
The first line is the CRS: an EPSG code, a PROJ string or `WGS84 UTM <zone><N|S>`. Then one line per
image: `name x y [z] [yaw pitch roll] [horizontal vertical accuracy] [extras]`, whitespace separated.
x/y are easting/northing, so longitude comes before latitude in a geographic CRS.

Angles: ODM normalises yaw/pitch/roll so that pitch 0 is a nadir camera and 90 looks forward (DJI's
gimbal pitch + 90), with yaw the heading of the image top. `pitch_zero` picks the convention of a file:
"nadir" (ODM's), "horizon" (gimbal angles as DJI writes them, our ypr of docs/formats.md), or "auto":
"horizon" when any pitch is below -45 degrees (impossible in ODM's convention), else "nadir".
ODM documents 0 0 0 as "angles not available": such rows get no attitude.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .attitude import matrix_to_ypr
from .frames import CRSError, from_wgs84, parse_crs
from .records import PosError, PosRecord
from .rows import ANGLE_RANGE, STD_RANGE, PosRow, check_number, position_bounds, rows_to_records

_UTM = re.compile(r"^WGS84\s+UTM\s+(\d{1,2})\s*([NS])$", re.IGNORECASE)


def parse_crs_line(line: str) -> str:
    """The CRS of a geo.txt header as a string pyproj accepts; CRSError if unknown."""
    text = line.strip()
    m = _UTM.match(text)
    if m:
        zone = int(m.group(1))
        if not 1 <= zone <= 60:
            raise CRSError(f"unknown CRS {text!r}: UTM zone {zone} is not in 1..60")
        text = f"EPSG:{(32600 if m.group(2).upper() == 'N' else 32700) + zone}"
    parse_crs(text)
    return text


def _attitude(values: list[float], pitch_zero: str) -> tuple[float, float, float] | None:
    yaw, pitch, roll = values
    if yaw == 0.0 and pitch == 0.0 and roll == 0.0:
        return None
    return (yaw, pitch - 90.0, roll) if pitch_zero == "nadir" else (yaw, pitch, roll)


def parse_geo_txt(text: str, source: str = "<geo.txt>", pitch_zero: str = "auto") -> list[PosRecord]:
    """Parse geo.txt text. Raises PosError listing every bad line (line, column, reason)."""
    if pitch_zero not in ("auto", "nadir", "horizon"):
        raise ValueError(f"pitch_zero must be auto, nadir or horizon, not {pitch_zero!r}")
    lines = text.splitlines()
    header = next(((i, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")), None)
    if header is None:
        raise PosError([f"{source}: empty file (the first line must name the CRS)"])
    try:
        crs = parse_crs_line(header[1])
    except CRSError as e:
        raise PosError([f"{source} line {header[0] + 1}: {e}"]) from None
    bounds = position_bounds(parse_crs(crs).is_geographic)
    geographic = parse_crs(crs).is_geographic
    errors: list[str] = []
    rows: list[PosRow] = []
    raw_att: list[tuple[int, list[float]]] = []
    for lineno, line in enumerate(lines[header[0] + 1 :], start=header[0] + 2):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        where = f"{source} line {lineno}"
        if len(parts) < 3:
            errors.append(f"{where}: expected `name x y [z] ...`, got {len(parts)} field(s)")
            continue
        if len(parts) in (5, 6):
            errors.append(f"{where}: {len(parts) - 4} angle(s); give yaw, pitch and roll together")
            continue
        n_err = len(errors)
        x_col, y_col = ("lon", "lat") if geographic else ("x", "y")
        x = check_number(errors, where, x_col, parts[1], bounds[1] if geographic else bounds[0])
        y = check_number(errors, where, y_col, parts[2], bounds[0] if geographic else bounds[1])
        z = check_number(errors, where, "z", parts[3]) if len(parts) > 3 else 0.0
        att = None
        if len(parts) >= 7:
            att = [
                check_number(errors, where, c, v, ANGLE_RANGE)
                for c, v in zip(("yaw", "pitch", "roll"), parts[4:7], strict=True)
            ]
        std = [None, None]
        for k, c in enumerate(("horizontal accuracy", "vertical accuracy")):
            if len(parts) > 7 + k:
                std[k] = check_number(errors, where, c, parts[7 + k], STD_RANGE)
        if len(errors) > n_err:
            continue
        coords = (y, x, z) if geographic else (x, y, z)
        rows.append(PosRow(where, parts[0], coords, std=(std[0], std[1], None)))  # type: ignore[arg-type]
        if att is not None:
            raw_att.append((len(rows) - 1, att))  # type: ignore[arg-type]
    if errors:
        raise PosError(errors)
    if pitch_zero == "auto":
        pitch_zero = "horizon" if any(a[1] < -45.0 for _, a in raw_att) else "nadir"
    for i, a in raw_att:
        rows[i].attitude = _attitude(a, pitch_zero)
    return rows_to_records(rows, crs, source)


def read_geo_txt(path: str | Path, pitch_zero: str = "auto") -> list[PosRecord]:
    """Read an ODM geo.txt file (see the module docstring for its angle conventions)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise PosError([f"{path}: cannot read: {e}"]) from None
    return parse_geo_txt(text, source=str(path), pitch_zero=pitch_zero)


def write_geo_txt(
    path: str | Path, records: Iterable[PosRecord], crs: str = "EPSG:4326", bare_names: bool = False
) -> Path:
    """Write records as geo.txt (angles in ODM's convention: pitch 0 = nadir; accuracies when known).

    `bare_names` writes file names without the set folder, as ODM expects for its flat image folder.
    """
    records = list(records)
    geographic = parse_crs(crs).is_geographic
    a, b, c = from_wgs84(crs, *(np.array([getattr(r, k) for r in records]) for k in ("lat", "lon", "h")))
    lines = [crs]
    for i, r in enumerate(records):
        x, y = (b[i], a[i]) if geographic else (a[i], b[i])
        fmt = "{:.10f}" if geographic else "{:.4f}"
        fields = [
            r.name.rsplit("/", 1)[-1] if bare_names else r.name,
            fmt.format(x),
            fmt.format(y),
            f"{c[i]:.4f}",
        ]
        if r.R_world_from_cam is not None or r.std_xy is not None or r.std_z is not None:
            if r.R_world_from_cam is None:
                fields += ["0", "0", "0"]
            else:
                yaw, pitch, roll = matrix_to_ypr(r.R_world_from_cam)
                fields += [f"{yaw:.5f}", f"{pitch + 90.0:.5f}", f"{roll:.5f}"]
        if r.std_xy is not None or r.std_z is not None:
            fields += [f"{r.std_xy or 0.0:.3f}", f"{r.std_z or 0.0:.3f}"]
        lines.append(" ".join(fields))
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
