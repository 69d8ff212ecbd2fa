"""The documented midview POS CSV (docs/formats.md): read with per-row validation, and write."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .attitude import matrix_to_opk, matrix_to_ypr, opk_to_matrix, ypr_to_matrix
from .frames import WGS84_3D, CRSError, from_wgs84, parse_crs, to_wgs84
from .records import PosError, PosRecord

GEO_COLS = ("lat", "lon", "h")
PROJ_COLS = ("x", "y", "z")
YPR_COLS = ("yaw", "pitch", "roll")
OPK_COLS = ("omega", "phi", "kappa")
STD_COLS = ("std_xy", "std_z", "std_att")
RANGES = {"lat": (-90.0, 90.0), "lon": (-180.0, 180.0)}
ANGLE_RANGE = (-360.0, 360.0)


def _directives(lines: list[str]) -> dict[str, str]:
    out = {}
    for line in lines:
        body = line.lstrip("#").strip()
        if ":" in body:
            k, v = body.split(":", 1)
            out[k.strip().lower()] = v.strip()
    return out


def read_pos_csv(path: str | Path) -> list[PosRecord]:
    """Parse a POS CSV. Raises PosError listing every bad row (line, column, reason)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise PosError([f"{path}: cannot read: {e}"]) from None
    return parse_pos_csv(text, source=str(path))


@dataclass
class _Layout:
    """What the comment lines and the header say: the CRS, the columns and where they are."""

    crs: str
    pos_cols: tuple[str, ...]
    att_cols: tuple[str, ...]
    col: dict[str, int]
    n_cols: int  # header fields
    first_line: int  # line number of the first data row


def _layout(lines: list[str], source: str) -> tuple[_Layout, Iterator[list[str]]]:
    """The file's layout and a reader of its data rows; PosError for a bad CRS, header or attitude."""
    n_comment = 0
    while n_comment < len(lines) and (lines[n_comment].startswith("#") or not lines[n_comment].strip()):
        n_comment += 1
    meta = _directives([ln for ln in lines[:n_comment] if ln.startswith("#")])
    crs = meta.get("crs", WGS84_3D)
    try:
        geographic = parse_crs(crs).is_geographic
    except CRSError as e:
        raise PosError([f"{source}: {e}"]) from None
    reader = csv.reader(io.StringIO("\n".join(lines[n_comment:])))
    header = [h.strip().lower() for h in next(reader, [])]
    if not header:
        raise PosError([f"{source}: no header row"])
    pos_cols = GEO_COLS if geographic else PROJ_COLS
    missing = [c for c in ("name", *pos_cols) if c not in header]
    if missing:
        kind = "geographic" if geographic else "projected"
        raise PosError([f"{source}: header lacks {', '.join(missing)} (required for the {kind} CRS {crs})"])
    att = meta.get("attitude")
    att_cols: tuple[str, ...] = ()
    if att == "opk" or (att is None and all(c in header for c in OPK_COLS)):
        att_cols = OPK_COLS
    elif att == "ypr" or (att is None and all(c in header for c in YPR_COLS)):
        att_cols = YPR_COLS
    elif att is not None:
        raise PosError([f"{source}: unknown attitude convention {att!r} (use ypr or opk)"])
    if att_cols and not all(c in header for c in att_cols):
        raise PosError([f"{source}: attitude {att} needs columns {', '.join(att_cols)}"])
    col = {c: i for i, c in enumerate(header)}
    return _Layout(crs, pos_cols, att_cols, col, len(header), n_comment + 2), reader


def _number(raw: str, c: str, where: str, errors: list[str], optional: bool = False) -> float | None:
    """The value of column c (None, with the reason appended to errors, when it is not a finite number
    in the column's range; None for an empty optional cell)."""
    raw = raw.strip()
    if optional and raw == "":
        return None
    try:
        v = float(raw)
    except ValueError:
        errors.append(f"{where}, column {c}: {raw!r} is not a number")
        return None
    if not math.isfinite(v):
        errors.append(f"{where}, column {c}: {raw!r} is not finite")
        return None
    lo, hi = RANGES.get(c, ANGLE_RANGE if c in YPR_COLS + OPK_COLS else (-math.inf, math.inf))
    if c in STD_COLS:
        lo = 0.0
    if not lo <= v <= hi:
        errors.append(f"{where}, column {c}: {v} is outside [{lo}, {hi}]")
        return None
    return v


def _rows(lay: _Layout, reader: Iterator[list[str]], source: str, errors: list[str]) -> list[tuple]:
    """[(line, name, position, attitude or None, stds)] of the valid rows; the others' reasons in errors."""
    rows = []
    seen: dict[str, int] = {}
    n_cols = lay.n_cols
    for lineno, row in enumerate(reader, start=lay.first_line):
        if not row or all(not c.strip() for c in row) or row[0].startswith("#"):
            continue
        where = f"{source} line {lineno}"
        if len(row) != n_cols:
            errors.append(f"{where}: {len(row)} fields, the header has {n_cols}")
            continue
        name = row[lay.col["name"]].strip()
        if not name:
            errors.append(f"{where}: empty image name")
            continue
        if name in seen:
            errors.append(f"{where}: duplicate name {name!r} (first on line {seen[name]})")
            continue
        seen[name] = lineno
        n_err = len(errors)
        p = [_number(row[lay.col[c]], c, where, errors) for c in lay.pos_cols]
        a = None
        if lay.att_cols and any(row[lay.col[c]].strip() for c in lay.att_cols):  # attitude may be absent
            a = [_number(row[lay.col[c]], c, where, errors) for c in lay.att_cols]
        s = [_number(row[lay.col[c]], c, where, errors, True) if c in lay.col else None for c in STD_COLS]
        if len(errors) == n_err:
            rows.append((lineno, name, p, a, s))
    return rows


def parse_pos_csv(text: str, source: str = "<pos>") -> list[PosRecord]:
    """The records of a POS CSV's text. Raises PosError listing every bad row (line, column, reason)."""
    lay, reader = _layout(text.splitlines(), source)
    errors: list[str] = []
    rows = _rows(lay, reader, source, errors)
    if errors:
        raise PosError(errors)
    if not rows:
        raise PosError([f"{source}: no POS rows"])
    arr = np.array([r[2] for r in rows], float)
    lat, lon, h = to_wgs84(lay.crs, arr[:, 0], arr[:, 1], arr[:, 2])
    records = []
    for i, (_, name, _, a, s) in enumerate(rows):
        R = None
        if a is not None:
            R = opk_to_matrix(*a) if lay.att_cols == OPK_COLS else ypr_to_matrix(*a)
        records.append(
            PosRecord(
                name=name,
                lat=float(lat[i]),
                lon=float(lon[i]),
                h=float(h[i]),
                R_world_from_cam=R,
                std_xy=s[0],
                std_z=s[1],
                std_att=s[2],
                crs=lay.crs,
            )
        )
    return records


def write_pos_csv(
    path: str | Path, records: Iterable[PosRecord], crs: str = WGS84_3D, attitude: str = "ypr"
) -> Path:
    """Write records in the documented format; positions in `crs`, attitude as ypr or opk."""
    records = list(records)
    geographic = parse_crs(crs).is_geographic
    pos_cols = GEO_COLS if geographic else PROJ_COLS
    att_cols = YPR_COLS if attitude == "ypr" else OPK_COLS
    a, b, c = from_wgs84(crs, *(np.array([getattr(r, k) for r in records]) for k in ("lat", "lon", "h")))
    buf = io.StringIO()
    buf.write(f"# midview-pos v1\n# crs: {crs}\n# attitude: {attitude}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["name", *pos_cols, *att_cols, *STD_COLS])
    pfmt = "{:.10f}" if geographic else "{:.4f}"
    for i, r in enumerate(records):
        if r.R_world_from_cam is None:
            angles = ["", "", ""]
        else:
            conv = matrix_to_ypr if attitude == "ypr" else matrix_to_opk
            angles = [f"{v:.5f}" for v in conv(r.R_world_from_cam)]
        std = ["" if v is None else f"{v:.3f}" for v in (r.std_xy, r.std_z, r.std_att)]
        w.writerow([r.name, pfmt.format(a[i]), pfmt.format(b[i]), f"{c[i]:.4f}", *angles, *std])
    path = Path(path)
    path.write_text(buf.getvalue(), encoding="utf-8")
    return path
