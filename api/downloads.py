"""Streaming stored objects through the API (the local backend has no presigned URLs)."""

from __future__ import annotations

from collections.abc import Iterator
from urllib.parse import quote

from fastapi.responses import StreamingResponse

from shared.storage import Storage

CHUNK = 1024 * 1024


def content_disposition(filename: str) -> str:
    """An attachment header with an ASCII fallback name and the UTF-8 name (RFC 6266 / 5987)."""
    fallback = "".join(c if 32 <= ord(c) < 127 and c not in '"\\' else "_" for c in filename)
    return f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{quote(filename, safe='')}"


def stream_object(storage: Storage, key: str, filename: str, content_type: str | None) -> StreamingResponse:
    """A response streaming a stored object; opened before the response starts, so a missing object is
    a 404 (StorageKeyError) rather than a broken stream."""
    stat = storage.stat(key)
    body = storage.open_read(key)

    def chunks() -> Iterator[bytes]:
        with body:
            while chunk := body.read(CHUNK):
                yield chunk

    headers = {"Content-Length": str(stat.size), "Content-Disposition": content_disposition(filename)}
    if stat.etag:
        headers["ETag"] = f'"{stat.etag}"'
    return StreamingResponse(chunks(), media_type=content_type or "application/octet-stream", headers=headers)
