"""Image intake shared by direct and multipart uploads: file name checks, decode checks, and storing a
batch all-or-nothing."""

from __future__ import annotations

import hashlib
import logging
import re
import unicodedata
import warnings
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import BinaryIO

import cv2
import numpy as np
from sqlalchemy.orm import Session

from shared.db import crud
from shared.db.models import Image, Project
from shared.images import IMAGE_SUFFIXES, ImageError
from shared.storage import Storage
from shared.storage.keys import component, image_key_for_name

log = logging.getLogger("midview.api")

CONTENT_TYPES = {
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".png": "image/png",
    ".tif": "image/tiff",
    ".tiff": "image/tiff",
}
MAX_FILENAME_BYTES = 255
CHUNK = 1024 * 1024
SHA256_RE = re.compile(r"^[0-9a-fA-F]{64}$")


def sanitize_filename(raw: str) -> str:
    """The file name of an upload without any folder part (`C:\\x\\A1.JPG` -> `A1.JPG`), NFC-normalised;
    ValueError when empty, hidden, too long, holding control characters or not an image suffix."""
    name = unicodedata.normalize("NFC", raw.replace("\\", "/").rsplit("/", 1)[-1].strip())
    if not name or name in (".", ".."):
        raise ValueError(f"{raw!r}: empty file name")
    if name.startswith("."):
        raise ValueError(f"{raw!r}: hidden file names are not accepted")
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise ValueError(f"{raw!r}: control characters in the file name")
    if len(name.encode()) > MAX_FILENAME_BYTES:
        raise ValueError(f"{raw!r}: file name longer than {MAX_FILENAME_BYTES} bytes")
    if PurePath(name).suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"{name!r}: not an image file (accepted: {', '.join(sorted(IMAGE_SUFFIXES))})")
    return component(name, "file name")


def image_name(image_set: str, filename: str) -> str:
    """`aerial` + `A1.jpg` -> `aerial/A1.jpg` (docs/formats.md)."""
    return f"{image_set}/{filename}"


def check_image_name(name: str) -> tuple[str, str]:
    """Validate a full image name SET/FILE: (set, sanitised file name); ValueError otherwise."""
    image_set, sep, filename = name.partition("/")
    if not sep or image_set not in ("aerial", "ground"):
        raise ValueError(f"image name {name!r}: expected aerial/FILE or ground/FILE")
    clean = sanitize_filename(filename)
    if clean != filename:
        raise ValueError(f"image name {name!r}: the file part must be a plain file name")
    return image_set, clean


def declared_sha256(values: list[str], filenames: list[str]) -> tuple[dict[str, str], list[str]]:
    """The client's SHA-256 per file from `sha256` form fields: ({file name: lower-case digest}, errors).

    Each value is `FILENAME:HEX` (FILENAME as sent or as sanitised; the digest is after the last colon),
    or a bare `HEX` when the request holds exactly one file. A malformed digest, a name that is no file
    of the request, or a file given two digests is an error."""
    out: dict[str, str] = {}
    errors: list[str] = []
    for value in values:
        raw_name, sep, digest = value.strip().rpartition(":")
        where = f"sha256 field {value[:100]!r}"
        if not sep and len(filenames) == 1:
            raw_name = filenames[0]
        elif not sep:
            errors.append(f"{where}: expected FILENAME:HEX (the request holds several files)")
            continue
        if not SHA256_RE.match(digest):
            errors.append(f"{where}: not a hex SHA-256 (64 hex digits)")
            continue
        try:
            name = sanitize_filename(raw_name)
        except ValueError:
            name = raw_name
        if name not in filenames:
            errors.append(f"{where}: {raw_name!r} is no file of this request")
        elif name in out:
            errors.append(f"{where}: {name} has two digests")
        else:
            out[name] = digest.lower()
    return out, errors


def jpeg_check(data: bytes, filename: str) -> tuple[int, int] | None:
    """(width, height) of a JPEG decoded in full with libjpeg-turbo in strict mode: corrupt entropy-coded
    data between intact markers (which OpenCV decodes to grey blocks with a warning on stderr) is an
    ImageError. None for what it cannot decode otherwise (a CMYK JPEG): left to OpenCV."""
    import simplejpeg

    try:
        img = simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=True, fastdct=True, fastupsample=True)
    except ValueError as e:
        text = str(e)
        if "corrupt" in text.lower() or "premature" in text.lower() or "extraneous" in text.lower():
            raise ImageError(f"{filename}: corrupt JPEG ({text})") from None
        return None
    if img.size == 0:
        raise ImageError(f"{filename}: cannot decode image")
    return int(img.shape[1]), int(img.shape[0])


class ImageTooLarge(ImageError):
    """An image whose header claims more pixels than the limit (nothing of it was decoded)."""


def header_pixels(path: Path) -> tuple[int, str] | None:
    """(pixels, "W x H") that an image file's header claims, read without decoding its pixels (Pillow
    reads the header only); None when Pillow does not know the format (left to the full decode)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                w, h = int(im.size[0]), int(im.size[1])
                return w * h, f"{w} x {h}"
    except Image.DecompressionBombError as e:  # over twice Pillow's own limit: its message has the count
        found = re.search(r"\((\d+) pixels\)", str(e))
        n = int(found.group(1)) if found else 2**62
        return n, f"{n}"
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return None


def decode_check(path: Path, filename: str, max_pixels: int | None = None) -> tuple[int, int]:
    """(width, height) of an image file, decoded in full; ImageError naming filename when it is truncated
    (JPEG without its end-of-image marker) or cannot be decoded, ImageTooLarge when its header claims
    more than max_pixels pixels (checked before anything is decoded: a decompression bomb)."""
    if max_pixels is not None:
        claimed = header_pixels(path)
        if claimed is not None and claimed[0] > max_pixels:
            raise ImageTooLarge(f"{filename}: {claimed[1]} pixels exceed the limit of {max_pixels} pixels")
    data = np.fromfile(path, np.uint8)
    if data.size == 0:
        raise ImageError(f"{filename}: empty file")
    is_jpeg = data[:2].tobytes() == b"\xff\xd8"
    if PurePath(filename).suffix.lower() in (".jpg", ".jpeg") and not is_jpeg:
        raise ImageError(f"{filename}: not a JPEG file (no start-of-image marker)")
    if is_jpeg and data[-2:].tobytes() != b"\xff\xd9":
        raise ImageError(f"{filename}: truncated JPEG (no end-of-image marker)")
    if is_jpeg:
        size = jpeg_check(data.tobytes(), filename)  # one full decode, strict
        if size is not None:
            return size
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise ImageError(f"{filename}: cannot decode image")
    height, width = img.shape[:2]
    return int(width), int(height)


def exif_meta(path: Path) -> dict:
    """What a job must know of an image's EXIF without reading it again: its focal length in pixels
    (`exif_focal_px`, None when the EXIF gives none: then the project needs a cameras.json)."""
    from services.pos.exif import focal_px, read_exif

    try:
        focal = focal_px(read_exif(path))
    except (ImageError, OSError, ValueError):
        focal = None
    return {"exif_focal_px": focal}


def hash_stream(f: BinaryIO, dest: Path | None = None) -> tuple[str, int]:
    """(sha256, size) of a stream, optionally copied to dest on the way."""
    h, size = hashlib.sha256(), 0
    out = open(dest, "wb") if dest is not None else None  # noqa: SIM115
    try:
        while chunk := f.read(CHUNK):
            h.update(chunk)
            size += len(chunk)
            if out is not None:
                out.write(chunk)
    finally:
        if out is not None:
            out.close()
    return h.hexdigest(), size


@dataclass
class CheckedImage:
    """An image file that passed the checks, ready to store."""

    name: str  # aerial/A0001.jpg
    path: Path
    sha256: str
    size: int
    width: int
    height: int
    uploaded_as: str | None = None
    meta: dict | None = None  # exif_meta

    @property
    def content_type(self) -> str:
        return CONTENT_TYPES.get(PurePath(self.name).suffix.lower(), "application/octet-stream")


def store_images(
    session: Session, storage: Storage, project: Project, images: list[CheckedImage]
) -> list[tuple[Image, bool]]:
    """Register and store a batch all-or-nothing: [(row, created)]. The rows are inserted first (the
    unique name holds off a concurrent upload of the same name until commit), then the new objects
    written, then the transaction committed; on any failure the rows are rolled back and the objects
    written by this call deleted. Same bytes under an existing name: the existing row (created False);
    other bytes: ConflictError."""
    written: list[str] = []
    results: list[tuple[Image, bool]] = []
    try:
        for im in images:
            key = image_key_for_name(project.tenant_id, project.id, im.name)
            meta = {
                **(im.meta or {}),
                **({"uploaded_as": im.uploaded_as} if im.uploaded_as and im.uploaded_as != im.name else {}),
            }
            row, created = crud.add_image(
                session,
                project.id,
                im.name,
                sha256=im.sha256,
                size_bytes=im.size,
                storage_key=key,
                width=im.width,
                height=im.height,
                metadata=meta or None,
            )
            if created or not storage.exists(row.storage_key):  # also repairs a lost object
                storage.put_file(row.storage_key, im.path, content_type=im.content_type)
                if created:
                    written.append(row.storage_key)
            results.append((row, created))
        session.commit()
    except BaseException:
        session.rollback()
        for key in written:
            try:
                storage.delete(key)
            except Exception:  # keep the original error
                log.exception("could not delete %s after a failed upload", key)
        raise
    return results
