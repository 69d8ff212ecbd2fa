"""Resumable multipart uploads of large images.

1. `POST /projects/{p}/uploads` {name, size, sha256?} -> an upload id, the part size and count;
2. for each part n: `GET .../uploads/{u}/parts/{n}` -> where to PUT it: a presigned storage URL (S3; no
   API key, the response's ETag header is the part's ETag) or the API route
   `PUT .../uploads/{u}/parts/{n}` (local storage; with the API key; returns the ETag);
   parts can go in parallel and be retried; the client keeps the ETags;
3. `POST .../uploads/{u}/complete` {parts: [{part_number, etag}]} -> the object is assembled, checked
   (size, sha256 when given, full decode) and registered as an image; a failing check deletes it (422);
4. `DELETE .../uploads/{u}` aborts.
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, HTTPException, Request, Response, status
from fastapi import Path as PathParam
from starlette.concurrency import run_in_threadpool

from api import upload_state
from api.deps import ProjectDep, SessionDep, SettingsDep, StorageDep
from api.ingest import CONTENT_TYPES, check_image_name, decode_check, hash_stream
from api.schemas import (
    ImageOut,
    PartOut,
    PartUrl,
    UploadComplete,
    UploadCreate,
    UploadedImage,
    UploadOut,
)
from api.upload_state import UploadState
from shared.db import crud
from shared.db.models import Project, utcnow
from shared.images import ImageError
from shared.storage import Storage, StorageError, StorageKeyError
from shared.storage.keys import image_key_for_name

router = APIRouter(prefix="/projects/{project_id}/uploads", tags=["uploads"])
log = logging.getLogger("midview.api")

UploadId = Annotated[str, PathParam(description="Upload id")]
PartNumber = Annotated[int, PathParam(ge=1, le=10_000)]


def _load(storage: Storage, project: Project, upload_id: str) -> UploadState:
    try:
        return upload_state.load(storage, project.tenant_id, project.id, upload_id)
    except StorageKeyError:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"upload {upload_id} not found") from None


def _out(state: UploadState, storage: Storage) -> UploadOut:
    presigned = storage.presigned_part_url(state.key, state.storage_upload_id, 1) is not None
    return UploadOut(
        id=state.id,
        name=state.name,
        size=state.size,
        sha256=state.sha256,
        part_size=state.part_size,
        part_count=state.part_count,
        parts_via="presigned" if presigned else "api",
        created_at=state.created_at,
    )


def _part_size(state: UploadState, n: int) -> int:
    if not 1 <= n <= state.part_count:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"part {n} outside 1..{state.part_count} of this upload"
        )
    return state.part_size if n < state.part_count else state.size - state.part_size * (state.part_count - 1)


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
    if upload_state.active_for_names(storage, project.tenant_id, project.id, {body.name}):
        raise HTTPException(status.HTTP_409_CONFLICT, f"an upload of {body.name!r} is already in progress")
    key = image_key_for_name(project.tenant_id, project.id, body.name)
    part_size, part_count = upload_state.plan_parts(body.size, settings.upload_part_size)
    content_type = CONTENT_TYPES.get(Path(body.name).suffix.lower())
    state = UploadState(
        id=upload_state.new_upload_id(),
        name=body.name,
        key=key,
        storage_upload_id=storage.create_multipart(key, content_type=content_type),
        size=body.size,
        sha256=body.sha256.lower() if body.sha256 else None,
        part_size=part_size,
        part_count=part_count,
        created_at=utcnow(),
    )
    upload_state.save(storage, project.tenant_id, project.id, state)
    log.info("project %s: upload %s of %s started (%d parts)", project.id, state.id, body.name, part_count)
    return _out(state, storage)


@router.get("", response_model=list[UploadOut])
def list_uploads(project: ProjectDep, storage: StorageDep) -> list[UploadOut]:
    return [_out(s, storage) for s in upload_state.list_uploads(storage, project.tenant_id, project.id)]


@router.get("/{upload_id}", response_model=UploadOut)
def get_upload(project: ProjectDep, storage: StorageDep, upload_id: UploadId) -> UploadOut:
    return _out(_load(storage, project, upload_id), storage)


@router.get("/{upload_id}/parts/{part_number}", response_model=PartUrl)
def part_url(
    request: Request,
    project: ProjectDep,
    storage: StorageDep,
    settings: SettingsDep,
    upload_id: UploadId,
    part_number: PartNumber,
) -> PartUrl:
    """Where to PUT part n: a presigned storage URL when the backend has them, else this API."""
    state = _load(storage, project, upload_id)
    size = _part_size(state, part_number)
    url = storage.presigned_part_url(state.key, state.storage_upload_id, part_number)
    if url is not None:
        return PartUrl(
            part_number=part_number,
            url=url,
            expires_in=settings.s3_presign_expiry_s,
            needs_auth=False,
            size=size,
        )
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
    request: Request, project: ProjectDep, storage: StorageDep, upload_id: UploadId, part_number: PartNumber
) -> PartOut:
    """Receive one part through the API (any backend); its size must be the planned one."""
    state = await run_in_threadpool(_load, storage, project, upload_id)
    expected = _part_size(state, part_number)
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
            etag = await run_in_threadpool(
                storage.upload_part, state.key, state.storage_upload_id, part_number, buf
            )
        except StorageKeyError:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"upload {upload_id} not found") from None
    return PartOut(part_number=part_number, etag=etag)


def _verify(storage: Storage, state: UploadState, tmp: Path) -> tuple[str, int, int, int]:
    """(sha256, size, width, height) of the assembled object; ValueError/ImageError when it fails."""
    filename = state.name.split("/", 1)[1]
    local = tmp / "image"
    with storage.open_read(state.key) as body:
        sha256, size = hash_stream(body, local)
    if size != state.size:
        raise ValueError(f"{filename}: {size} bytes assembled, {state.size} announced")
    if state.sha256 is not None and sha256 != state.sha256:
        raise ValueError(f"{filename}: sha256 {sha256} does not match the announced {state.sha256}")
    width, height = decode_check(local, filename)
    return sha256, size, width, height


@router.post(
    "/{upload_id}/complete",
    status_code=status.HTTP_201_CREATED,
    response_model=UploadedImage,
    responses={
        409: {"description": "The name was taken meanwhile"},
        422: {"description": "Parts missing or wrong, or the image failed its checks (deleted)"},
    },
)
def complete_upload(
    body: UploadComplete,
    project: ProjectDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    upload_id: UploadId,
) -> UploadedImage:
    state = _load(storage, project, upload_id)
    numbers = sorted(p.part_number for p in body.parts)
    if numbers != list(range(1, state.part_count + 1)):
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"expected parts 1..{state.part_count} once each, got {numbers[:20]}",
        )
    if crud.get_image(session, project.id, state.name) is not None:
        with contextlib.suppress(StorageError):
            storage.abort_multipart(state.key, state.storage_upload_id)
        upload_state.delete(storage, project.tenant_id, project.id, state.id)
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"image {state.name!r} was stored meanwhile; upload dropped"
        )
    try:
        storage.complete_multipart(
            state.key, state.storage_upload_id, [(p.part_number, p.etag) for p in body.parts]
        )
    except (ValueError, StorageError) as e:  # wrong ETag, missing part: the client may fix and retry
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"cannot assemble the parts: {e}"
        ) from None
    with tempfile.TemporaryDirectory(prefix="midview-complete-", dir=settings.upload_tmp_dir) as tmp:
        try:
            sha256, size, width, height = _verify(storage, state, Path(tmp))
        except (ValueError, ImageError) as e:
            storage.delete(state.key)
            upload_state.delete(storage, project.tenant_id, project.id, state.id)
            raise HTTPException(
                status.HTTP_422_UNPROCESSABLE_CONTENT,
                {"message": "upload rejected and deleted", "errors": [str(e)]},
            ) from None
    try:
        row, created = crud.add_image(
            session,
            project.id,
            state.name,
            sha256=sha256,
            size_bytes=size,
            storage_key=state.key,
            width=width,
            height=height,
            metadata={"upload_id": state.id},
        )
        session.commit()
    except Exception:
        session.rollback()
        log.error("upload %s: %s could not be registered after assembly", state.id, state.name)
        raise
    finally:
        upload_state.delete(storage, project.tenant_id, project.id, state.id)
    log.info("project %s: upload %s completed as %s (%d bytes)", project.id, state.id, state.name, size)
    return UploadedImage(**ImageOut.model_validate(row).model_dump(), created=created)


@router.delete("/{upload_id}", status_code=status.HTTP_204_NO_CONTENT)
def abort_upload(project: ProjectDep, storage: StorageDep, upload_id: UploadId) -> Response:
    state = _load(storage, project, upload_id)
    with contextlib.suppress(StorageKeyError):
        storage.abort_multipart(state.key, state.storage_upload_id)
    upload_state.delete(storage, project.tenant_id, project.id, state.id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
