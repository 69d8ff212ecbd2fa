"""Read POS from any supported source (the rows of the text formats: rows.py).

`read_pos` dispatches on the path: a folder of images (EXIF/XMP), `.csv` (docs/formats.md), `.json`
(json_format.py), `.txt` (OpenDroneMap geo.txt, odm.py); other extensions are sniffed by content.
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Iterable
from pathlib import Path, PurePath

from .records import PosError, PosRecord, check_against_images


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
