"""The rows of the text POS formats (CSV, geo.txt, JSON) before they become PosRecords: their value
checks and their conversion to WGS84 records, shared by the readers."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .attitude import opk_to_matrix, ypr_to_matrix
from .frames import CRSError, parse_crs, to_wgs84
from .records import PosError, PosRecord

LAT_RANGE = (-90.0, 90.0)
LON_RANGE = (-180.0, 180.0)
ANGLE_RANGE = (-360.0, 360.0)
STD_RANGE = (0.0, math.inf)


@dataclass
class PosRow:
    """One parsed but not yet converted POS entry; `where` names its file and line for errors."""

    where: str
    name: str
    coords: tuple[float, float, float]  # (lat, lon, h) for a geographic CRS, else (x, y, z)
    attitude: tuple[float, float, float] | None = None
    convention: str = "ypr"  # "ypr" or "opk" (docs/formats.md)
    std: tuple[float | None, float | None, float | None] = field(default=(None, None, None))


def check_number(
    errors: list[str],
    where: str,
    column: str,
    raw: object,
    bounds: tuple[float, float] = (-math.inf, math.inf),
    optional: bool = False,
) -> float | None:
    """`raw` as a finite float within `bounds`; else append a message to `errors` and return None."""
    if raw is None or (isinstance(raw, str) and not raw.strip()):
        if not optional:
            errors.append(f"{where}, column {column}: missing value")
        return None
    if isinstance(raw, bool):
        errors.append(f"{where}, column {column}: {raw!r} is not a number")
        return None
    try:
        v = float(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        errors.append(f"{where}, column {column}: {raw!r} is not a number")
        return None
    if not math.isfinite(v):
        errors.append(f"{where}, column {column}: {raw!r} is not finite")
        return None
    lo, hi = bounds
    if not lo <= v <= hi:
        errors.append(f"{where}, column {column}: {v} is outside [{lo}, {hi}]")
        return None
    return v


def position_bounds(geographic: bool) -> tuple[tuple[float, float], ...]:
    """Bounds of the three position values: (lat, lon, h) when geographic, else unbounded (x, y, z)."""
    free = (-math.inf, math.inf)
    return (LAT_RANGE, LON_RANGE, free) if geographic else (free, free, free)


def rows_to_records(rows: list[PosRow], crs: str, source: str) -> list[PosRecord]:
    """Check names (non-empty, unique), convert positions from `crs` to WGS84 and attitudes to matrices."""
    try:
        parse_crs(crs)
    except CRSError as e:
        raise PosError([f"{source}: {e}"]) from None
    errors, seen = [], {}
    for r in rows:
        if not r.name:
            errors.append(f"{r.where}: empty image name")
        elif r.name in seen:
            errors.append(f"{r.where}: duplicate name {r.name!r} (first at {seen[r.name]})")
        else:
            seen[r.name] = r.where
    if errors:
        raise PosError(errors)
    if not rows:
        raise PosError([f"{source}: no POS entries"])
    arr = np.array([r.coords for r in rows], float)
    lat, lon, h = to_wgs84(crs, arr[:, 0], arr[:, 1], arr[:, 2])
    out = []
    for i, r in enumerate(rows):
        R = None
        if r.attitude is not None:
            R = opk_to_matrix(*r.attitude) if r.convention == "opk" else ypr_to_matrix(*r.attitude)
        out.append(PosRecord(r.name, float(lat[i]), float(lon[i]), float(h[i]), R, *r.std, crs=crs))
    return out
