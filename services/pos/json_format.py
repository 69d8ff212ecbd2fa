"""POS as JSON: the fields of the POS CSV (docs/formats.md) as objects.

Accepted shapes (keys case-insensitive, optional values may be null or absent):

```
[{"name": "aerial/A0001.jpg", "lat": 55.70, "lon": 13.19, "h": 112.3, "yaw": 90, "pitch": -45, "roll": 0}]
{"crs": "EPSG:32633", "attitude": "opk", "records": [{"name": ..., "x": ..., "y": ..., "z": ...}]}
{"crs": "EPSG:4979", "records": {"aerial/A0001.jpg": {"lat": ..., "lon": ..., "h": ...}}}
{"aerial/A0001.jpg": {"lat": ..., "lon": ..., "h": ...}}
```
The CRS defaults to EPSG:4979; the attitude convention is `attitude` or else decided by the keys
(yaw/pitch/roll or omega/phi/kappa), as in the CSV.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .attitude import matrix_to_opk, matrix_to_ypr
from .frames import WGS84_3D, CRSError, from_wgs84, parse_crs
from .records import PosError, PosRecord
from .rows import ANGLE_RANGE, STD_RANGE, PosRow, check_number, position_bounds, rows_to_records

GEO_KEYS = ("lat", "lon", "h")
PROJ_KEYS = ("x", "y", "z")
YPR_KEYS = ("yaw", "pitch", "roll")
OPK_KEYS = ("omega", "phi", "kappa")
STD_KEYS = ("std_xy", "std_z", "std_att")
HEADER_KEYS = {"crs", "attitude", "records", "images", "format", "version"}


def _entries(doc: Any, source: str) -> tuple[dict, list[tuple[str, dict]]]:
    """(header, [(where, entry)]) of the accepted JSON shapes."""
    header: dict = {}
    if isinstance(doc, dict) and (HEADER_KEYS & {k.lower() for k in doc}):
        header = {k.lower(): v for k, v in doc.items() if k.lower() in HEADER_KEYS - {"records", "images"}}
        doc = doc.get("records", doc.get("images", []))
    if isinstance(doc, dict):  # {name: {fields}}
        out = []
        for name, v in doc.items():
            if not isinstance(v, dict):
                raise PosError([f"{source}: entry {name!r} is not an object"])
            out.append((f"{source} entry {name!r}", {**v, "name": name}))
        return header, out
    if isinstance(doc, list):
        out = []
        for i, v in enumerate(doc):
            if not isinstance(v, dict):
                raise PosError([f"{source}: record {i} is not an object"])
            out.append((f"{source} record {i}", v))
        return header, out
    raise PosError([f"{source}: expected a list of records or an object of them"])


def parse_pos_json(text: str, source: str = "<pos.json>") -> list[PosRecord]:
    """Parse POS JSON text. Raises PosError listing every bad record (record, field, reason)."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise PosError([f"{source}: not valid JSON: {e}"]) from None
    header, entries = _entries(doc, source)
    crs = str(header.get("crs") or WGS84_3D)
    try:
        geographic = parse_crs(crs).is_geographic
    except CRSError as e:
        raise PosError([f"{source}: {e}"]) from None
    att = header.get("attitude")
    if att not in (None, "ypr", "opk"):
        raise PosError([f"{source}: unknown attitude convention {att!r} (use ypr or opk)"])
    pos_keys = GEO_KEYS if geographic else PROJ_KEYS
    bounds = position_bounds(geographic)
    errors: list[str] = []
    rows = []
    for where, raw in entries:
        e = {str(k).lower(): v for k, v in raw.items()}
        n_err = len(errors)
        name = e.get("name")
        if not isinstance(name, str):
            errors.append(f"{where}: name must be a string, not {name!r}")
            continue
        coords = [check_number(errors, where, k, e.get(k), b) for k, b in zip(pos_keys, bounds, strict=True)]
        conv = att or ("opk" if any(e.get(k) is not None for k in OPK_KEYS) else "ypr")
        keys = OPK_KEYS if conv == "opk" else YPR_KEYS
        angles = None
        if any(e.get(k) is not None for k in keys):
            angles = tuple(check_number(errors, where, k, e.get(k), ANGLE_RANGE) for k in keys)
        std = tuple(check_number(errors, where, k, e.get(k), STD_RANGE, optional=True) for k in STD_KEYS)
        if len(errors) == n_err:
            rows.append(PosRow(where, name.strip(), tuple(coords), angles, conv, std))  # type: ignore[arg-type]
    if errors:
        raise PosError(errors)
    return rows_to_records(rows, crs, source)


def read_pos_json(path: str | Path) -> list[PosRecord]:
    """Read a POS JSON file (shapes in the module docstring)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise PosError([f"{path}: cannot read: {e}"]) from None
    return parse_pos_json(text, source=str(path))


def write_pos_json(
    path: str | Path, records: Iterable[PosRecord], crs: str = WGS84_3D, attitude: str = "ypr"
) -> Path:
    """Write records as `{"crs", "attitude", "records": [...]}`."""
    records = list(records)
    geographic = parse_crs(crs).is_geographic
    keys = GEO_KEYS if geographic else PROJ_KEYS
    a, b, c = from_wgs84(crs, *(np.array([getattr(r, k) for r in records]) for k in GEO_KEYS))
    conv = matrix_to_ypr if attitude == "ypr" else matrix_to_opk
    att_keys = YPR_KEYS if attitude == "ypr" else OPK_KEYS
    out = []
    for i, r in enumerate(records):
        d: dict[str, Any] = {"name": r.name, keys[0]: float(a[i]), keys[1]: float(b[i]), keys[2]: float(c[i])}
        if r.R_world_from_cam is not None:
            d.update(zip(att_keys, (round(v, 6) for v in conv(r.R_world_from_cam)), strict=True))
        d.update(
            {k: v for k, v in zip(STD_KEYS, (r.std_xy, r.std_z, r.std_att), strict=True) if v is not None}
        )
        out.append(d)
    path = Path(path)
    path.write_text(json.dumps({"crs": crs, "attitude": attitude, "records": out}, indent=1))
    return path
