"""Read POS from any supported source, and the row checks the text formats share.

`read_pos` dispatches on the path: a folder of images (EXIF/XMP), `.csv` (docs/formats.md), `.json`
(json_format.py), `.txt` (OpenDroneMap geo.txt, odm.py); other extensions are sniffed by content.
"""

from __future__ import annotations

import inspect
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import numpy as np

from .attitude import opk_to_matrix, ypr_to_matrix
from .frames import CRSError, parse_crs, to_wgs84
from .records import PosError, PosRecord, check_against_images

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


def match_names(records: list[PosRecord], image_names: Iterable[str]) -> list[PosRecord]:
    """Give bare file names (as geo.txt and EXIF-less tools write them) the image's set prefix.

    A record named `DJI_0018.JPG` becomes `aerial/DJI_0018.JPG` when exactly one image has that file
    name; full names and unknown names are left alone (check_against_images reports the latter).
    """
    by_base: dict[str, list[str]] = {}
    for n in image_names:
        by_base.setdefault(n.rsplit("/", 1)[-1], []).append(n)
    for r in records:
        if "/" not in r.name and len(by_base.get(r.name, [])) == 1:
            r.name = by_base[r.name][0]
    return records


def sniff_format(path: Path) -> str:
    """'exif', 'csv', 'json' or 'geo' for a POS path, from its extension or else its first line."""
    if path.is_dir():
        return "exif"
    if path.suffix.lower() in (".csv", ".json"):
        return path.suffix.lower()[1:]
    try:
        with open(path, encoding="utf-8-sig") as f:
            head = f.read(4096)
    except (OSError, UnicodeDecodeError) as e:
        raise PosError([f"{path}: cannot read: {e}"]) from None
    return sniff_text(head, path.name)


def sniff_text(text: str, filename: str | None = None) -> str:
    """'csv', 'json' or 'geo' for POS text: from the file name's extension, else its first line."""
    suffix = PurePath(filename or "").suffix.lower()
    if suffix in (".csv", ".json"):
        return suffix[1:]
    first = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
    if first.startswith(("[", "{")):
        return "json"
    if first.startswith("#") or "," in first:
        return "csv"
    return "geo"


def _readers() -> dict:
    from .exif import read_pos_exif
    from .json_format import read_pos_json
    from .odm import read_geo_txt
    from .pos_csv import read_pos_csv

    return {"exif": read_pos_exif, "csv": read_pos_csv, "json": read_pos_json, "geo": read_geo_txt}


def reader_options(reader) -> set[str]:
    """The keyword options of a format reader (its parameters after the path, `names` excepted)."""
    params = list(inspect.signature(reader).parameters)[1:]
    return {p for p in params if p != "names"}


def read_pos(
    path: str | os.PathLike,
    image_names: Iterable[str] | None = None,
    **kwargs,
) -> list[PosRecord]:
    """POS records from a CSV, JSON, geo.txt file or a folder of images (their EXIF/XMP).

    With `image_names`, bare file names in the POS are mapped to the images' full names
    (`aerial/X.jpg`) and every image must have a record and every record an image (PosError otherwise).
    `kwargs` are options of the readers (`pitch_zero` for geo.txt; `altitude`, `attitude`, `takeoff_h`
    for EXIF): each goes to the reader that takes it and is ignored by the others, so one call can
    carry the options of every format; an option no reader takes is a TypeError.
    """
    path = Path(path)
    readers = _readers()
    known = {o for r in readers.values() for o in reader_options(r)}
    unknown = sorted(set(kwargs) - known)
    if unknown:
        raise TypeError(
            f"read_pos: unknown option(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})"
        )
    if not path.exists():
        raise PosError([f"{path}: no such file or folder"])
    kind = sniff_format(path)
    reader = readers[kind]
    options = {k: v for k, v in kwargs.items() if k in reader_options(reader)}
    if kind == "exif":
        records = reader(path, names=None if image_names is None else list(image_names), **options)
    else:
        records = reader(path, **options)
    if image_names is not None:
        names = list(image_names)
        match_names(records, names)
        check_against_images(records, names)
    return records
