"""Checking an assembled upload and registering it as an image, in the request or in the background.

`finish_upload` reads the assembled object back, hashes it, decodes it in full and registers the image
(the upload row goes in the same transaction); a failing check raises UploadRejected. POST
.../complete runs it in the request by default. With `wait: false` the request ends once the parts are
assembled (202, the upload `verifying`) and `Verifier` runs it on a worker thread of the API process:
the bytes' transfer is what the client waits for, and the next image's parts travel while this one is
decoded. A check that fails leaves the upload `rejected` with the reason (its object deleted); a job
cannot start while a project has uploads verifying or rejected (409).

Durability: the upload row holds the claim (`verify_started_at`). `Verifier.sweep` (at startup and every
sweep_s) claims again the uploads left `verifying` longer than stale_s (an API process that died
mid-check) and checks them; two API processes never take the same upload (the claim is one UPDATE).
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timedelta
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from api.ingest import decode_check, exif_meta, hash_stream
from shared.db import crud
from shared.db.models import Image, Upload, utcnow
from shared.images import ImageError
from shared.storage import Storage, StorageError, StorageKeyError

log = logging.getLogger("midview.api.verify")


class UploadRejected(Exception):
    """The assembled object failed a check (the message says which)."""


def check_object(
    storage: Storage, upload: Upload, tmp: Path, max_pixels: dict[str, int] | None = None
) -> tuple[str, int, int, int, dict]:
    """(sha256, size, width, height, exif_meta) of the assembled object; UploadRejected when it fails
    (`max_pixels`: the largest image per set, checked on the header before anything is decoded)."""
    filename = upload.name.split("/", 1)[1]
    local = tmp / "image"
    try:
        with storage.open_read(upload.storage_key) as body:
            sha256, size = hash_stream(body, local)
    except StorageKeyError:
        raise UploadRejected(f"{filename}: the assembled object is missing from the storage") from None
    if size != upload.size_bytes:
        raise UploadRejected(f"{filename}: {size} bytes assembled, {upload.size_bytes} announced")
    if upload.sha256 is not None and sha256 != upload.sha256:
        raise UploadRejected(f"{filename}: sha256 {sha256} does not match the announced {upload.sha256}")
    try:
        width, height = decode_check(local, filename, (max_pixels or {}).get(upload.name.split("/", 1)[0]))
    except ImageError as e:
        raise UploadRejected(str(e)) from None
    return sha256, size, width, height, exif_meta(local)


def finish_upload(
    session: Session,
    storage: Storage,
    upload: Upload,
    tmp_dir: str | None = None,
    max_pixels: dict[str, int] | None = None,
) -> tuple[Image, bool]:
    """Check the assembled object and register it as an image, deleting the upload row, in one
    transaction (committed): (image row, created). UploadRejected (nothing committed) when a check
    fails; the caller deletes the object and records or answers the reason."""
    with tempfile.TemporaryDirectory(prefix="midview-complete-", dir=tmp_dir) as tmp:
        sha256, size, width, height, meta = check_object(storage, upload, Path(tmp), max_pixels)
    name, uid = upload.name, upload.id
    try:
        row, created = crud.add_image(
            session,
            upload.project_id,
            name,
            sha256=sha256,
            size_bytes=size,
            storage_key=upload.storage_key,
            width=width,
            height=height,
            metadata={"upload_id": uid, **meta},
        )
        session.delete(upload)
        session.commit()
    except Exception:
        session.rollback()
        log.error("upload %s: %s could not be registered after assembly", uid, name)
        raise
    log.info("project %s: upload %s completed as %s (%d bytes)", upload.project_id, uid, name, size)
    return row, created


class Verifier:
    """Checks `verifying` uploads on `workers` threads of this process (see the module); `maker` makes
    the sessions that write (BEGIN IMMEDIATE on SQLite), `read_maker` those that only read."""

    def __init__(
        self,
        maker: sessionmaker[Session],
        read_maker: sessionmaker[Session],
        storage: Storage,
        tmp_dir: str | None = None,
        workers: int = 1,
        stale_s: float = 300.0,
        max_pixels: dict[str, int] | None = None,
        expiry_s: float = 24 * 3600.0,
    ) -> None:
        self.maker, self.read_maker, self.storage = maker, read_maker, storage
        self.tmp_dir, self.stale_s, self.max_pixels = tmp_dir, stale_s, max_pixels
        self.expiry_s = expiry_s
        self.pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="verify")

    def submit(self, upload_id: str):
        """Check the upload (already claimed) on a worker thread; the future's result: its state."""
        return self.pool.submit(self.run, upload_id)

    def run(self, upload_id: str) -> str:
        """Check one claimed upload: registered (`done`), `rejected` (with the reason, its object
        deleted), or `gone` (another process finished it, or it was aborted)."""
        with self.maker() as session:
            upload = session.get(Upload, upload_id)
            if upload is None or upload.state != "verifying":
                return "gone"
            try:
                finish_upload(session, self.storage, upload, self.tmp_dir, self.max_pixels)
                return "done"
            except UploadRejected as e:
                session.rollback()
                with contextlib.suppress(StorageKeyError):
                    self.storage.delete(upload.storage_key)
                upload.state, upload.error = "rejected", str(e)
                session.commit()
                log.warning("upload %s of %s rejected: %s", upload.id, upload.name, e)
                return "rejected"
            except Exception:
                log.exception("upload %s: the check failed; the sweep tries again", upload_id)
                return "error"

    def claim(self, session: Session, upload_id: str, now: datetime | None = None) -> bool:
        """Take an upload for checking: true when it is verifying and unclaimed, or its claim is older
        than stale_s (one UPDATE: two processes never both win); the caller commits."""
        now = now or utcnow()
        cutoff = now - timedelta(seconds=self.stale_s)
        result = session.execute(
            sa.update(Upload)
            .where(
                Upload.id == upload_id,
                Upload.state == "verifying",
                sa.or_(Upload.verify_started_at.is_(None), Upload.verify_started_at < cutoff),
            )
            .values(verify_started_at=now)
        )
        return getattr(result, "rowcount", 0) == 1  # an UPDATE's CursorResult

    def expire(self, now: datetime | None = None) -> list[str]:
        """Abort the uploads left open longer than expiry_s since they started (their parts deleted
        from the storage, their rows gone); their ids."""
        cutoff = (now or utcnow()) - timedelta(seconds=self.expiry_s)
        with self.read_maker() as session:  # no write lock (SQLite) while there is nothing to expire
            ids = session.scalars(
                sa.select(Upload.id).where(Upload.state == "open", Upload.created_at < cutoff)
            ).all()
        if not ids:
            return []
        with self.maker() as session:
            rows = session.scalars(sa.select(Upload).where(Upload.id.in_(ids), Upload.state == "open")).all()
            for upload in rows:
                with contextlib.suppress(StorageError):
                    self.storage.abort_multipart(upload.storage_key, upload.storage_upload_id)
                session.delete(upload)
                log.info("upload %s of %s expired: open since %s", upload.id, upload.name, upload.created_at)
            session.commit()
        return [u.id for u in rows]

    def sweep(self, now: datetime | None = None) -> list[str]:
        """Claim and check the uploads left verifying past their claim; their ids."""
        now = now or utcnow()
        cutoff = now - timedelta(seconds=self.stale_s)
        with self.read_maker() as session:  # no write lock (SQLite) while there is nothing to take
            ids = session.scalars(
                sa.select(Upload.id).where(
                    Upload.state == "verifying",
                    sa.or_(Upload.verify_started_at.is_(None), Upload.verify_started_at < cutoff),
                )
            ).all()
        if not ids:
            return []
        with self.maker() as session:
            taken = [i for i in ids if self.claim(session, i, now)]
            session.commit()
        for upload_id in taken:
            log.warning("upload %s was left verifying: checking it again", upload_id)
            self.submit(upload_id)
        return taken

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=False)
