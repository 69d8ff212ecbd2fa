"""POS uploads: pick the format, parse with services.pos, and check the rows against the project's images;
POS read from the stored images' EXIF/XMP."""

from __future__ import annotations

import importlib
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Literal

from services.pos import PosError, PosRecord, parse_pos_csv, sniff_text
from shared.images import ImageError
from shared.storage import Storage, StorageError

PosFormat = Literal["auto", "csv", "geotxt", "json"]

# format -> (module, function) of a text parser `parse(text, source) -> list[PosRecord]`
_PARSERS: dict[str, tuple[str, str]] = {
    "csv": ("services.pos.pos_csv", "parse_pos_csv"),
    "json": ("services.pos.json_format", "parse_pos_json"),
    "geotxt": ("services.pos.odm", "parse_geo_txt"),
}


def detect_format(text: str, filename: str | None) -> str:
    """csv, json or geotxt (the API's name of geo.txt) as services.pos sniffs them."""
    fmt = sniff_text(text, filename)
    return "geotxt" if fmt == "geo" else fmt


def _parser(fmt: str) -> Callable[..., list[PosRecord]]:
    if fmt == "csv":
        return parse_pos_csv
    module, name = _PARSERS[fmt]
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        raise PosError([f"POS format {fmt!r} is not supported by this installation"]) from None


def parse_pos_text(text: str, fmt: str, source: str) -> list[PosRecord]:
    """Parse POS text of a format (csv, json, geotxt); PosError listing every bad row."""
    return _parser(fmt)(text, source=source)


def _match_names(records: list[PosRecord], image_names: list[str]) -> None:
    """Bare file names (geo.txt, EXIF tools) -> the images' full names, when services.pos has it."""
    try:
        from services.pos.io import match_names
    except ImportError:
        return
    match_names(records, image_names)


@dataclass
class PosCheck:
    """Result of checking POS rows against the uploaded images."""

    errors: list[str] = field(default_factory=list)  # rows naming no image: refused
    warnings: list[str] = field(default_factory=list)  # images without a row: accepted


def check_against_project(
    records: list[PosRecord], image_names: Iterable[str], known: Iterable[str]
) -> PosCheck:
    """Rows must name uploaded images (errors); images lacking a row in both this upload and the stored
    POS (`known`) are warnings, since ground images may come without attitude or even position."""
    names = sorted(image_names)
    _match_names(records, names)
    have = {r.name for r in records}
    images = set(names)
    check = PosCheck()
    check.errors = [f"POS row {r.name!r} names no uploaded image" for r in records if r.name not in images]
    covered = have | set(known)
    check.warnings = [f"image {n!r} has no POS row" for n in names if n not in covered]
    return check


@dataclass
class ExifPos:
    """POS rows read from images' metadata, and what went wrong per image."""

    records: list[PosRecord] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)  # unreadable images, or no position: refused
    warnings: list[str] = field(default_factory=list)  # skipped images (skip_without_gps)


def _exif_record(
    storage: Storage, name: str, key: str, folder: Path, options: dict, errors: list[str]
) -> tuple[PosRecord | None, bool]:
    """(the POS row of one stored image from its EXIF/XMP, or None with the reasons appended to errors;
    whether the metadata lacks a position or the altitude asked for). The image is downloaded to folder
    and removed again."""
    from services.pos.exif import read_exif, record_from_exif

    local = folder / PurePath(name).name
    try:
        storage.download(key, local)
        data = read_exif(local)
    except (ImageError, StorageError) as e:
        errors.append(f"image {name!r}: {str(e).replace(str(local), name)}")
        return None, False
    finally:
        local.unlink(missing_ok=True)
    h = data.rel_alt if options.get("altitude") == "relative" else data.alt
    no_position = data.lat is None or data.lon is None or h is None
    return record_from_exif(name, data, errors=errors, **options), no_position


def pos_from_images(
    storage: Storage,
    images: Iterable[tuple[str, str]],
    options: dict,
    skip_without_gps: bool = False,
    tmp_dir: str | None = None,
) -> ExifPos:
    """POS rows of stored images [(name, storage key)] from their EXIF GPS and DJI XMP; options go to
    services.pos.exif.record_from_exif (altitude, attitude, takeoff_h). Images lacking a position or the
    altitude asked for are errors, or warnings with skip_without_gps; unreadable images are errors."""
    out = ExifPos()
    with tempfile.TemporaryDirectory(prefix="midview-exif-", dir=tmp_dir) as tmp:
        for name, key in images:
            problems: list[str] = []
            record, no_position = _exif_record(storage, name, key, Path(tmp), options, problems)
            if record is not None:
                out.records.append(record)
            elif skip_without_gps and no_position:
                out.warnings += [f"{p}; skipped" for p in problems]
            else:
                out.errors += problems
    return out
