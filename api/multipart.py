"""Streaming `multipart/form-data` reception: every file part goes straight to a temp file while its size
is counted against a limit and its SHA-256 computed, so a huge or endless upload is cut off early and
never held in memory (FastAPI's UploadFile would spool the whole request first)."""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import Request

MAX_FIELD_BYTES = 64 * 1024
EXTRA_FIELDS = 64  # text fields allowed beyond one per file (max_files)


class MultipartError(ValueError):
    """The request is not a usable multipart body (400/415/422 depending on `status`)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


class FileTooLarge(MultipartError):
    """A file part exceeded the size limit (413)."""

    def __init__(self, filename: str, limit: int) -> None:
        super().__init__(f"file {filename!r} exceeds the upload limit of {limit} bytes", status=413)
        self.filename, self.limit = filename, limit


@dataclass
class ReceivedFile:
    """One file part of the request, stored at `path`."""

    field: str
    filename: str
    path: Path
    content_type: str | None = None
    size: int = 0
    sha256: str = ""
    _hash: Any = dataclasses.field(default_factory=hashlib.sha256, repr=False)
    _file: IO[bytes] | None = dataclasses.field(default=None, repr=False)


def _decode(value: bytes) -> str:
    try:
        return value.decode("utf-8")
    except UnicodeDecodeError:
        return value.decode("latin-1")


class _Receiver:
    """python-multipart callbacks writing file parts to numbered files in `folder`."""

    def __init__(self, folder: Path, max_file_bytes: int, max_files: int) -> None:
        self.folder, self.max_file_bytes, self.max_files = folder, max_file_bytes, max_files
        self.files: list[ReceivedFile] = []
        self.fields: dict[str, list[str]] = {}
        self.max_fields = max_files + EXTRA_FIELDS
        self._field_count = 0
        self._headers: dict[bytes, bytes] = {}
        self._hname = self._hvalue = b""
        self._file: ReceivedFile | None = None
        self._field: tuple[str, bytearray] | None = None

    def on_part_begin(self) -> None:
        self._headers, self._file, self._field = {}, None, None

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._hname += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._hvalue += data[start:end]

    def on_header_end(self) -> None:
        self._headers[self._hname.strip().lower()] = self._hvalue.strip()
        self._hname = self._hvalue = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        name = _decode(options.get(b"name", b""))
        if b"filename" not in options:
            self._field_count += 1
            if self._field_count > self.max_fields:
                raise MultipartError(f"too many form fields in one request (at most {self.max_fields})", 413)
            self._field = (name, bytearray())
            return
        if len(self.files) >= self.max_files:
            raise MultipartError(f"too many files in one request (at most {self.max_files})", status=413)
        ctype = self._headers.get(b"content-type")
        rf = ReceivedFile(
            field=name,
            filename=_decode(options[b"filename"]),
            path=self.folder / f"{len(self.files):06d}.part",
            content_type=_decode(ctype) if ctype else None,
        )
        rf._file = open(rf.path, "wb")  # noqa: SIM115 - closed in on_part_end / close()
        self.files.append(rf)
        self._file = rf

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        chunk = data[start:end]
        rf = self._file
        if rf is None:
            if self._field is not None:
                if len(self._field[1]) + len(chunk) > MAX_FIELD_BYTES:
                    raise MultipartError(f"form field {self._field[0]!r} is too long", status=413)
                self._field[1].extend(chunk)
            return
        rf.size += len(chunk)
        if rf.size > self.max_file_bytes:
            raise FileTooLarge(rf.filename, self.max_file_bytes)
        rf._hash.update(chunk)
        assert rf._file is not None
        rf._file.write(chunk)

    def on_part_end(self) -> None:
        if self._file is not None:
            assert self._file._file is not None
            self._file._file.close()
            self._file.sha256 = self._file._hash.hexdigest()
        elif self._field is not None:
            self.fields.setdefault(self._field[0], []).append(_decode(bytes(self._field[1])))
        self._file = self._field = None

    def close(self) -> None:
        for rf in self.files:
            if rf._file is not None and not rf._file.closed:
                rf._file.close()


async def receive_files(
    request: Request, folder: Path, *, max_file_bytes: int, max_files: int
) -> tuple[list[ReceivedFile], dict[str, list[str]]]:
    """Read a multipart request body: (file parts written under folder, other form fields: every value
    of each, in order, since a field may repeat).

    Raises MultipartError (FileTooLarge when a file passes max_file_bytes; reading stops there)."""
    ctype, params = parse_options_header(request.headers.get("content-type"))
    if ctype != b"multipart/form-data":
        raise MultipartError("expected a multipart/form-data body", status=415)
    boundary = params.get(b"boundary")
    if not boundary:
        raise MultipartError("multipart body without a boundary")
    receiver = _Receiver(folder, max_file_bytes, max_files)
    callbacks: Any = {
        name: getattr(receiver, name)
        for name in (
            "on_part_begin",
            "on_part_data",
            "on_part_end",
            "on_header_field",
            "on_header_value",
            "on_header_end",
            "on_headers_finished",
        )
    }
    parser = MultipartParser(boundary, callbacks)
    try:
        async for chunk in request.stream():
            parser.write(chunk)
        parser.finalize()
    except FormParserError as e:
        raise MultipartError(f"invalid multipart body: {e}") from e
    finally:
        receiver.close()
    if any(not rf.sha256 for rf in receiver.files):
        raise MultipartError("incomplete multipart body (a file part has no end)")
    return receiver.files, receiver.fields
