"""Resumable image uploads through the API's multipart uploads: an image already stored with the same
digest is skipped, an upload left unfinished by a killed client is resumed from the parts the storage
holds, and only the missing parts are sent."""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from client.http import ApiError, MidviewClient, Upload

PartCallback = Callable[[str, int, int, int], None]  # (image name, part number, part count, bytes)


@dataclass(frozen=True)
class UploadResult:
    name: str
    # "uploaded", "resumed" (an unfinished upload completed), "present" (stored already) or "checking"
    # (sent before, the service still checking it)
    state: str
    parts_sent: int
    part_count: int
    bytes_sent: int


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _present(name: str, stored_sha256: str, digest: str) -> UploadResult:
    if stored_sha256 != digest:
        raise ValueError(
            f"{name}: the project holds another image of this name (sha256 {stored_sha256[:12]}..., "
            f"the file's is {digest[:12]}...); use another project or delete the stored image"
        )
    return UploadResult(name, "present", 0, 0, 0)


def _start_or_resume(
    mv: MidviewClient, project_id: str, name: str, size: int, digest: str | None, pending: Upload | None
) -> tuple[Upload, list[int], bool]:
    """(upload, part numbers to send, resumed): the unfinished upload of the same file, else a new one."""
    if pending is not None and pending["size"] == size and pending.get("sha256") in (None, digest):
        try:
            parts = mv.upload_parts(project_id, pending["id"])
            return pending, sorted({*parts["missing"], *parts["wrong_size"]}), True
        except ApiError as e:
            if e.status != 404:  # the storage forgot it: start again
                raise
    if pending is not None:  # another file's, or gone from the storage
        mv.abort_upload(project_id, pending["id"])
    upload = mv.create_upload(project_id, name, size, digest)
    return upload, list(range(1, upload["part_count"] + 1)), False


def _send_parts(
    mv: MidviewClient,
    project_id: str,
    upload: Upload,
    path: Path,
    todo: list[int],
    parallel: int,
    on_part: PartCallback | None,
) -> tuple[int, list[tuple[int, str]]]:
    """PUT the parts `todo` of the file, `parallel` at a time (each read where it lies); (bytes sent,
    [(part number, ETag)] in part order)."""
    size = upload["part_size"]
    lock = threading.Lock()
    urls = {u["part_number"]: u for u in upload.get("part_urls") or []}  # given with the start

    def send(fd: int, n: int) -> tuple[int, int, str]:
        data = os.pread(fd, size, (n - 1) * size)
        etag = mv.put_part(project_id, upload["id"], n, data, urls.get(n))
        if on_part is not None:
            with lock:
                on_part(upload["name"], n, upload["part_count"], len(data))
        return n, len(data), etag

    fd = os.open(path, os.O_RDONLY)
    try:
        if parallel <= 1 or len(todo) <= 1:
            done = [send(fd, n) for n in todo]
        else:
            with ThreadPoolExecutor(min(parallel, len(todo))) as pool:
                done = list(pool.map(lambda n: send(fd, n), todo))
    finally:
        os.close(fd)
    return sum(b for _, b, _ in done), sorted((n, etag) for n, _, etag in done)


def upload_image(
    mv: MidviewClient,
    project_id: str,
    name: str,
    path: Path,
    stored: dict[str, str] | None = None,
    pending: dict[str, Upload] | None = None,
    on_part: PartCallback | None = None,
    parallel: int = 4,
    wait: bool = True,
) -> UploadResult:
    """Upload `path` as image `name` (SET/FILE), `parallel` parts at a time. `stored` ({name: sha256} of
    the project's images) and `pending` ({name: upload} in progress) save a request per image when the
    caller lists them once. wait false: return once the parts are assembled, the service checking the
    image meanwhile (MidviewClient.wait_uploads_checked before using the images)."""
    size = path.stat().st_size
    if stored is None:
        stored = {im["name"]: im["sha256"] for im in mv.images(project_id)}
    if name in stored:
        return _present(name, stored[name], sha256_file(path))
    if pending is None:
        pending = {u["name"]: u for u in mv.uploads(project_id)}
    if pending.get(name, {}).get("state") == "verifying":  # sent before: being checked
        return UploadResult(name, "checking", 0, 0, 0)
    if pending.get(name, {}).get("state") == "rejected":  # its check failed: upload it again
        pending = {k: v for k, v in pending.items() if k != name}
    with ThreadPoolExecutor(1) as hasher:
        # a new upload: the file is hashed while its parts travel and the digest sent at completion;
        # resuming one: the digest first (is the unfinished upload this file's?)
        fresh = name not in pending
        hashing = hasher.submit(sha256_file, path)
        digest = None if fresh else hashing.result()
        try:
            upload, todo, resumed = _start_or_resume(mv, project_id, name, size, digest, pending.get(name))
        except ApiError as e:
            if e.status != 409:
                raise
            if isinstance(e.detail, dict) and e.detail.get("sha256"):  # stored meanwhile
                return _present(name, e.detail["sha256"], hashing.result())
            again = {u["name"]: u for u in mv.uploads(project_id)}  # started meanwhile: resume that one
            digest = hashing.result()
            upload, todo, resumed = _start_or_resume(mv, project_id, name, size, digest, again.get(name))
        sent, etags = _send_parts(mv, project_id, upload, path, todo, parallel, on_part)
        digest = hashing.result()
    every_part = len(etags) == upload["part_count"]  # else the storage lists them (resumed)
    try:
        mv.complete_upload(
            project_id,
            upload["id"],
            wait=wait,
            parts=etags if every_part else None,
            sha256=None if upload.get("sha256") else digest,
        )
    except ApiError as e:
        if e.status != 409:
            raise
        image = {im["name"]: im["sha256"] for im in mv.images(project_id)}.get(name)
        if image is None:
            raise
        return _present(name, image, digest)
    return UploadResult(name, "resumed" if resumed else "uploaded", len(todo), upload["part_count"], sent)
