"""Resumable multipart uploads of large images.

1. `POST /projects/{p}/uploads` {name, size, sha256?} -> an upload id, the part size and count (and with
   S3 the presigned URL of every part, up to 256 of them); at most one upload per image name is in
   progress (a database row, unique per project and name);
2. for each part n: `GET .../uploads/{u}/parts/{n}` (unless the start gave it) -> where to PUT it: a
   presigned storage URL (S3; no API key, the response's ETag header is the part's ETag) or the API route
   `PUT .../uploads/{u}/parts/{n}` (local storage; with the API key; returns the ETag);
   parts can go in parallel and be retried;
3. to resume (the client lost its ETags, or which parts arrived): `GET .../uploads/{u}/parts` lists the
   parts the storage holds (number, size, ETag) and those missing;
4. `POST .../uploads/{u}/complete` {parts: [{part_number, etag}]} (or {} to take the listed parts) -> the
   object is assembled, checked (size, sha256 when given, full decode) and registered as an image; a
   failing check deletes it (422). With `wait: false`: 202 once assembled, the check in the background
   (api/verify.py; the upload `verifying`, then gone into the images or `rejected` with the reason);
5. `DELETE .../uploads/{u}` aborts.
"""

from __future__ import annotations

import contextlib
import logging
import math
import tempfile
from pathlib import Path
from typing import Annotated, Any, BinaryIO, cast

from fastapi import APIRouter, HTTPException, Request, Response, status
from fastapi import Path as PathParam
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from api.deps import ProjectDep, SessionDep, SettingsDep, StorageDep
from api.ingest import CONTENT_TYPES, check_image_name
from api.schemas import (
    ImageOut,
    PartOut,
    PartUrl,
    ReceivedPart,
    UploadComplete,
    UploadCreate,
    UploadedImage,
    UploadOut,
    UploadParts,
)
from api.verify import UploadRejected, finish_upload
from shared.db import crud
from shared.db.crud import ConflictError
from shared.db.models import Project, Upload, utcnow
from shared.storage import Storage, StorageError, StorageKeyError
from shared.storage.base import MAX_PART_NUMBER
from shared.storage.keys import image_key_for_name

router = APIRouter(prefix="/projects/{project_id}/uploads", tags=["uploads"])
log = logging.getLogger("midview.api")

UploadId = Annotated[str, PathParam(description="Upload id")]
PartNumber = Annotated[int, PathParam(ge=1, le=10_000)]
MAX_PART_URLS = 256  # presigned part URLs given with the start of an upload (more: GET each)


def plan_parts(size: int, part_size: int) -> tuple[int, int]:
    """(part size, part count) for size bytes: part_size, grown when it would need more than 10000 parts."""
    part_size = max(part_size, math.ceil(size / MAX_PART_NUMBER))
    return part_size, max(1, math.ceil(size / part_size))


def _load(session: Session, project: Project, upload_id: str) -> Upload:
    upload = crud.get_upload(session, project.id, upload_id)
    if upload is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"upload {upload_id} not found")
    return upload


def _out(upload: Upload, storage: Storage) -> UploadOut:
    try:
        presigned = storage.presigned_part_url(upload.storage_key, upload.storage_upload_id, 1) is not None
    except StorageKeyError:  # assembled (verifying, rejected): the storage forgot the multipart upload
        presigned = False
    return UploadOut(
        id=upload.id,
        name=upload.name,
        size=upload.size_bytes,
        sha256=upload.sha256,
        part_size=upload.part_size,
        part_count=upload.part_count,
        parts_via="presigned" if presigned else "api",
        created_at=upload.created_at,
        state=upload.state,
        error=upload.error,
    )


def _part_size(upload: Upload, n: int) -> int:
    if not 1 <= n <= upload.part_count:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"part {n} outside 1..{upload.part_count} of this upload"
        )
    last = upload.size_bytes - upload.part_size * (upload.part_count - 1)
    return upload.part_size if n < upload.part_count else last


def _drop(session: Session, storage: Storage, upload: Upload, abort: bool = True) -> None:
    """Forget an upload (its row, committed), aborting its storage upload first when asked."""
    if abort:
        with contextlib.suppress(StorageError):
            storage.abort_multipart(upload.storage_key, upload.storage_upload_id)
    session.delete(upload)
    session.commit()


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=UploadOut,
    responses={
        409: {"description": "The image exists, or is being uploaded"},
        413: {"description": "Larger than max_upload_bytes"},
    },
)
def create_upload(
    body: UploadCreate, project: ProjectDep, session: SessionDep, storage: StorageDep, settings: SettingsDep
) -> UploadOut:
    """Start an upload. Only one upload of a name can be in progress: two concurrent starts of the same
    name cannot both succeed (the database's unique constraint decides; the loser gets 409)."""
    try:
        check_image_name(body.name)
    except ValueError as e:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(e)) from None
    if body.size > settings.max_upload_bytes:
        raise HTTPException(
            status.HTTP_413_CONTENT_TOO_LARGE,
            f"{body.name}: {body.size} bytes exceed the upload limit of {settings.max_upload_bytes} bytes",
        )
    existing = crud.get_image(session, project.id, body.name)
    if existing is not None:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            {"message": f"image {body.name!r} already exists", "sha256": existing.sha256},
        )
    busy = f"an upload of {body.name!r} is already in progress"
    crud.drop_rejected_upload(session, project.id, body.name)  # a new start replaces a failed check
    if crud.uploads_in_progress(session, project.id, [body.name]):
        raise HTTPException(status.HTTP_409_CONFLICT, busy)
    key = image_key_for_name(project.tenant_id, project.id, body.name)
    part_size, part_count = plan_parts(body.size, settings.upload_part_size)
    content_type = CONTENT_TYPES.get(Path(body.name).suffix.lower())
    storage_upload_id = storage.create_multipart(key, content_type=content_type)
    session.commit()  # end the read transaction: SQLite cannot turn a stale read snapshot into a write
    try:
        upload = crud.create_upload(
            session,
            project.id,
            body.name,
            storage_key=key,
            storage_upload_id=storage_upload_id,
            size_bytes=body.size,
            sha256=body.sha256,
            part_size=part_size,
            part_count=part_count,
        )
        session.commit()
    except BaseException as e:
        session.rollback()
        with contextlib.suppress(StorageError):
            storage.abort_multipart(key, storage_upload_id)
        if isinstance(e, ConflictError):  # a concurrent start of the same name won
            raise HTTPException(status.HTTP_409_CONFLICT, busy) from None
        raise
    log.info("project %s: upload %s of %s started (%d parts)", project.id, upload.id, body.name, part_count)
    out = _out(upload, storage)
    if out.parts_via == "presigned" and part_count <= MAX_PART_URLS:
        urls = [_presigned_part(upload, storage, settings, n) for n in range(1, part_count + 1)]
        out.part_urls = [u for u in urls if u is not None]
    return out


@router.get("", response_model=list[UploadOut])
def list_uploads(project: ProjectDep, session: SessionDep, storage: StorageDep) -> list[UploadOut]:
    return [_out(u, storage) for u in crud.list_uploads(session, project.id)]


@router.get("/{upload_id}", response_model=UploadOut)
def get_upload(
    project: ProjectDep, session: SessionDep, storage: StorageDep, upload_id: UploadId
) -> UploadOut:
    return _out(_load(session, project, upload_id), storage)


def _received(storage: Storage, upload: Upload, etags: dict[int, str] | None = None) -> list[ReceivedPart]:
    """The parts the storage holds for an upload (those `etags` names where a part was sent again);
    404 when the storage no longer knows it."""
    try:
        listed = storage.list_parts(upload.storage_key, upload.storage_upload_id, etags)
    except StorageKeyError:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"upload {upload.id}: the storage no longer has it; start again"
        ) from None
    return [ReceivedPart(part_number=p.part_number, size=p.size, etag=p.etag, last_modified=p.last_modified)
            for p in listed if 1 <= p.part_number <= upload.part_count]  # fmt: skip


@router.get("/{upload_id}/parts", response_model=UploadParts)
def list_parts(
    project: ProjectDep, session: SessionDep, storage: StorageDep, upload_id: UploadId
) -> UploadParts:
    """The parts received so far (number, size, ETag), read from the storage, and those still to send:
    a client that lost its ETags or was interrupted resumes from here and completes with these ETags."""
    upload = _load(session, project, upload_id)
    parts = _received(storage, upload)
    have = {p.part_number for p in parts}
    return UploadParts(
        id=upload.id,
        part_count=upload.part_count,
        parts=parts,
        missing=[n for n in range(1, upload.part_count + 1) if n not in have],
        wrong_size=[p.part_number for p in parts if p.size != _part_size(upload, p.part_number)],
    )


def _presigned_part(upload: Upload, storage: Storage, settings: Any, n: int) -> PartUrl | None:
    """Where to PUT part n straight to the storage (a presigned URL); None when it presigns nothing."""
    size = _part_size(upload, n)
    url = storage.presigned_part_url(upload.storage_key, upload.storage_upload_id, n, size=size)
    if url is None:
        return None
    return PartUrl(
        part_number=n, url=url, expires_in=settings.s3_presign_expiry_s, needs_auth=False, size=size
    )


@router.get("/{upload_id}/parts/{part_number}", response_model=PartUrl)
def part_url(
    request: Request,
    project: ProjectDep,
    storage: StorageDep,
    session: SessionDep,
    settings: SettingsDep,
    upload_id: UploadId,
    part_number: PartNumber,
) -> PartUrl:
    """Where to PUT part n: a presigned storage URL when the backend has them, else this API."""
    upload = _load(session, project, upload_id)
    size = _part_size(upload, part_number)
    presigned = _presigned_part(upload, storage, settings, part_number)
    if presigned is not None:
        return presigned
    api_url = request.url_for(
        "upload_part", project_id=project.id, upload_id=upload_id, part_number=part_number
    )
    return PartUrl(part_number=part_number, url=str(api_url), needs_auth=True, size=size)


@router.put(
    "/{upload_id}/parts/{part_number}",
    response_model=PartOut,
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
        }
    },
)
async def upload_part(
    request: Request,
    project: ProjectDep,
    session: SessionDep,
    storage: StorageDep,
    upload_id: UploadId,
    part_number: PartNumber,
) -> PartOut:
    """Receive one part through the API (any backend); its size must be the planned one."""
    upload = await run_in_threadpool(_load, session, project, upload_id)
    key, storage_upload_id = upload.storage_key, upload.storage_upload_id
    expected = _part_size(upload, part_number)
    await run_in_threadpool(session.close)  # hold no database connection while the bytes flow
    with tempfile.SpooledTemporaryFile(max_size=8 * 1024 * 1024) as buf:
        received = 0
        async for chunk in request.stream():
            received += len(chunk)
            if received > expected:
                raise HTTPException(
                    status.HTTP_413_CONTENT_TOO_LARGE, f"part {part_number} must be {expected} bytes"
                )
            buf.write(chunk)
        if received != expected:
            raise HTTPException(
                status.HTTP_422_UNPROCESSABLE_CONTENT,
                f"part {part_number} must be {expected} bytes, got {received}",
            )
        buf.seek(0)
        try:
            part = cast(BinaryIO, buf)
            etag = await run_in_threadpool(storage.upload_part, key, storage_upload_id, part_number, part)
        except StorageKeyError:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"upload {upload_id} not found") from None
    return PartOut(part_number=part_number, etag=etag)


def _parts_to_complete(storage: Storage, upload: Upload, body: UploadComplete) -> list[tuple[int, str]]:
    """[(part number, ETag)] from the request, or else from the storage's list; 422 unless every part
    1..part_count is there once."""
    if body.parts is not None:
        parts = [(p.part_number, p.etag) for p in body.parts]
    else:
        parts = [(p.part_number, p.etag) for p in _received(storage, upload)]
    numbers = sorted(n for n, _ in parts)
    if numbers != list(range(1, upload.part_count + 1)):
        missing = sorted(set(range(1, upload.part_count + 1)) - set(numbers))
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"expected parts 1..{upload.part_count} once each, got {numbers[:20]}"
            + (f"; missing {missing[:20]}" if missing else ""),
        )
    return parts


def _check_part_sizes(storage: Storage, upload: Upload, parts: list[tuple[int, str]]) -> None:
    """422 when a part to assemble is not its planned size (sent around the signed length): the
    parts are never assembled, nor downloaded, and the client may send that part again."""
    wrong = [
        f"part {p.part_number} is {p.size} bytes, not {_part_size(upload, p.part_number)}"
        for p in _received(storage, upload, dict(parts))
        if p.size != _part_size(upload, p.part_number)
    ]
    if wrong:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "; ".join(wrong[:10]))


@router.post(
    "/{upload_id}/complete",
    status_code=status.HTTP_201_CREATED,
    response_model=UploadedImage,
    responses={
        202: {"model": UploadOut, "description": "wait false: assembled; checked in the background"},
        409: {"description": "The name was taken meanwhile"},
        422: {"description": "Parts missing or wrong, or the image failed its checks (deleted)"},
    },
)
def complete_upload(
    request: Request,
    body: UploadComplete,
    project: ProjectDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    upload_id: UploadId,
) -> UploadedImage | Response:
    """Assemble the parts (those given with their ETags, or without `parts` those the storage lists),
    check the image and register it; the upload is then finished. With `wait: false`, answer 202 once
    the parts are assembled: the check runs in the background (api/verify.py) and GET .../uploads/{u}
    shows the upload `verifying`, then gone (GET .../images has the image) or `rejected` with the reason."""
    upload = _load(session, project, upload_id)
    if upload.state != "open":
        raise HTTPException(status.HTTP_409_CONFLICT, f"upload {upload_id} is {upload.state}, not open")
    if body.sha256 is not None:
        if upload.sha256 is not None and upload.sha256 != body.sha256.lower():
            raise HTTPException(
                status.HTTP_422_UNPROCESSABLE_CONTENT,
                f"sha256 {body.sha256} differs from the {upload.sha256} announced at the start",
            )
        upload.sha256 = body.sha256.lower()
    parts = _parts_to_complete(storage, upload, body)
    _check_part_sizes(storage, upload, parts)
    if crud.get_image(session, project.id, upload.name) is not None:
        _drop(session, storage, upload)
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"image {upload.name!r} was stored meanwhile; upload dropped"
        )
    try:
        storage.complete_multipart(upload.storage_key, upload.storage_upload_id, parts)
    except (ValueError, StorageError) as e:  # wrong ETag, missing part: the client may fix and retry
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"cannot assemble the parts: {e}"
        ) from None
    if not body.wait:
        upload.state, upload.verify_started_at = "verifying", utcnow()
        session.commit()
        request.app.state.verifier.submit(upload.id)
        out = _out(upload, storage).model_dump_json()
        return Response(out, status_code=status.HTTP_202_ACCEPTED, media_type="application/json")
    try:
        row, created = finish_upload(
            session, storage, upload, settings.upload_tmp_dir, settings.max_image_pixels
        )
    except UploadRejected as e:
        storage.delete(upload.storage_key)
        _drop(session, storage, upload, abort=False)
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            {"message": "upload rejected and deleted", "errors": [str(e)]},
        ) from None
    return UploadedImage(**ImageOut.model_validate(row).model_dump(), created=created)


@router.delete("/{upload_id}", status_code=status.HTTP_204_NO_CONTENT)
def abort_upload(
    project: ProjectDep, session: SessionDep, storage: StorageDep, upload_id: UploadId
) -> Response:
    _drop(session, storage, _load(session, project, upload_id))
    return Response(status_code=status.HTTP_204_NO_CONTENT)
