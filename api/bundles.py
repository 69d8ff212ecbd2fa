"""A job's results as named products, each one zip file streamed through the API: what a GIS user loads
(the GIS layers of the combined model, the orthophoto and the report) and what a photogrammetrist opens
in COLMAP (the combined model, its georeference and its report).

Members are streamed from the storage into the zip as it is sent (ZIP_STORED: the layers and models are
binary or already compact), so a bundle of any size costs the API a chunk of memory at a time.
"""

from __future__ import annotations

import fnmatch
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass

from shared.db.models import Artifact
from shared.storage import Storage

CHUNK = 1024 * 1024


@dataclass(frozen=True)
class Bundle:
    name: str
    help: str
    patterns: tuple[str, ...]  # artifact names (fnmatch) the bundle holds


BUNDLES = {
    b.name: b
    for b in (
        Bundle("gis", "GIS layers of the combined model (GeoPackage, GeoJSON, OPK, LAS), the survey's "
               "orthophoto (GeoTIFF, WGS84) and the report",
               ("combined/gis/*", "views/ortho/orthophoto.tif", "combined/report.json")),
        Bundle("colmap", "the combined COLMAP model (cameras, images, points), its georeference and report",
               ("combined/sparse/*", "combined/georef.json", "combined/report.json")),
    )
}  # fmt: skip


def members(bundle: Bundle, artifacts: list[Artifact]) -> list[Artifact]:
    """The job's artifacts the bundle holds, by name, the newest of each name."""
    newest: dict[str, Artifact] = {}
    for a in sorted(artifacts, key=lambda a: a.created_at):
        if any(fnmatch.fnmatchcase(a.name, p) for p in bundle.patterns):
            newest[a.name] = a
    return [newest[n] for n in sorted(newest)]


class _Pipe:
    """A write-only file for zipfile whose bytes are taken out as they are written."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.pos = 0

    def write(self, b: bytes) -> int:
        self.buf += b
        self.pos += len(b)
        return len(b)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass

    def take(self) -> bytes:
        out = bytes(self.buf)
        self.buf.clear()
        return out


def stream_zip(storage: Storage, files: list[tuple[str, str]]) -> Iterator[bytes]:
    """The zip of stored objects [(name in the zip, storage key)], in chunks as it is built."""
    pipe = _Pipe()
    with zipfile.ZipFile(pipe, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, key in files:
            with storage.open_read(key) as src, zf.open(name, "w", force_zip64=True) as dst:
                while chunk := src.read(CHUNK):
                    dst.write(chunk)
                    yield pipe.take()
            yield pipe.take()
    yield pipe.take()
