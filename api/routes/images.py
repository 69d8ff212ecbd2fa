"""Image upload (streamed multipart form), listing, download and deletion."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request, Response, status
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from api.deps import ProjectDep, SessionDep, SettingsDep, StorageDep
from api.downloads import stream_object
from api.ingest import (
    CONTENT_TYPES,
    CheckedImage,
    declared_sha256,
    decode_check,
    exif_meta,
    image_name,
    sanitize_filename,
    store_images,
)
from api.multipart import MultipartError, ReceivedFile, receive_files
from api.schemas import ImageOut, ImageSet, ImageUploadResult, UploadedImage
from shared.db import crud
from shared.db.crud import ConflictError
from shared.db.models import Image, Project
from shared.images import ImageError

router = APIRouter(prefix="/projects/{project_id}/images", tags=["images"])
log = logging.getLogger("midview.api")

SHA256_FIELD = "sha256"
UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {
                        "files": {"type": "array", "items": {"type": "string", "format": "binary"}},
                        SHA256_FIELD: {
                            "type": "array",
                            "items": {"type": "string", "pattern": "^(.+:)?[0-9a-fA-F]{64}$"},
                            "description": "Optional, one per file to check: FILENAME:HEX, the SHA-256 of "
                            "the file's bytes (a bare HEX when the request holds one file)",
                        },
                    },
                    "required": ["files"],
                }
            }
        },
    }
}


def _rejected(errors: list[str], what: str = "rejected") -> HTTPException:
    n = len(errors)
    message = f"{n} file{'s' if n > 1 else ''} {what}; nothing was stored"
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, {"message": message, "errors": errors})


def _named(files: list[ReceivedFile], errors: list[str]) -> list[tuple[ReceivedFile, str]]:
    """(file, sanitised file name) of every received file whose name is acceptable and not repeated."""
    out: list[tuple[ReceivedFile, str]] = []
    seen: set[str] = set()
    for rf in files:
        try:
            filename = sanitize_filename(rf.filename)
        except ValueError as e:
            errors.append(str(e))
            continue
        if filename in seen:
            errors.append(f"{filename}: given twice in this request")
            continue
        seen.add(filename)
        out.append((rf, filename))
    return out


def _check_files(
    files: list[ReceivedFile], image_set: str, sha256_fields: list[str], max_pixels: int | None = None
) -> list[CheckedImage]:
    """Names, declared SHA-256, pixel limit and decode checks of every received file; 422 listing every
    bad one."""
    errors: list[str] = []
    named = _named(files, errors)
    declared, sha_errors = declared_sha256(sha256_fields, [filename for _, filename in named])
    errors += sha_errors
    out: list[CheckedImage] = []
    for rf, filename in named:
        want = declared.get(filename)
        if want is not None and rf.sha256 != want:
            errors.append(
                f"{filename}: sha256 {rf.sha256} of the received bytes does not match the declared {want}"
            )
            continue
        try:
            width, height = decode_check(rf.path, filename, max_pixels)
        except ImageError as e:
            errors.append(str(e))
            continue
        out.append(
            CheckedImage(
                image_name(image_set, filename),
                rf.path,
                rf.sha256,
                rf.size,
                width,
                height,
                rf.filename,
                exif_meta(rf.path),
            )
        )
    if errors:
        raise _rejected(errors)
    return out


def _busy_names(session: Session, project: Project, names: set[str]) -> None:
    busy = crud.uploads_in_progress(session, project.id, names)
    if busy:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"a multipart upload is in progress for {', '.join(busy)}; nothing was stored",
        )


@router.post(
    "",
    response_model=ImageUploadResult,
    status_code=status.HTTP_201_CREATED,
    openapi_extra=UPLOAD_BODY,
    responses={
        200: {"description": "Every file was already stored with the same bytes"},
        409: {"description": "A name is taken by different bytes; nothing was stored"},
        413: {"description": "A file exceeds max_upload_bytes; nothing was stored"},
        422: {
            "description": "A file is not a decodable image, or its bytes do not match its declared "
            "sha256; nothing was stored"
        },
    },
)
async def upload_images(
    request: Request,
    response: Response,
    project: ProjectDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    image_set: Annotated[ImageSet, Query(alias="set", description="aerial or ground")],
) -> ImageUploadResult:
    """Upload one or many images (multipart form, any field name) into a set. All-or-nothing: if any file
    is too large, undecodable, truncated, badly named or conflicts with a stored image, nothing is stored.
    The same bytes again under the same name are accepted as they are (`created: false`).

    Integrity: for each file to check, add a text field `sha256` = `FILENAME:HEX` (the file name as sent,
    the SHA-256 of its bytes in hex; the field repeats, one per file; a bare `HEX` is enough when the
    request holds one file). The API hashes the bytes as they stream in: a file whose digest differs,
    a malformed digest or one naming no file of the request rejects the whole request (422, one reason
    per file) and nothing is stored. Files without a `sha256` field are not checked this way.
    E.g. `curl -F files=@A1.jpg -F sha256=A1.jpg:$(sha256sum A1.jpg | cut -c1-64) ...`."""
    # no database connection (on SQLite: no write lock) while the bytes flow: a slow client holds nothing
    await run_in_threadpool(session.close)
    with tempfile.TemporaryDirectory(prefix="midview-upload-", dir=settings.upload_tmp_dir) as tmp:
        try:
            files, fields = await receive_files(
                request,
                Path(tmp),
                max_file_bytes=settings.max_upload_bytes,
                max_files=settings.max_files_per_request,
            )
        except MultipartError as e:
            suffix = "; nothing was stored" if e.status == 413 else ""
            raise HTTPException(e.status, f"{e}{suffix}") from None
        if not files:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "no file in the request")
        checked = await run_in_threadpool(
            _check_files,
            files,
            image_set,
            fields.get(SHA256_FIELD, []),
            settings.max_image_pixels.get(image_set),
        )
        await run_in_threadpool(_busy_names, session, project, {c.name for c in checked})
        try:
            results = await run_in_threadpool(store_images, session, storage, project, checked)
        except ConflictError as e:
            raise HTTPException(status.HTTP_409_CONFLICT, f"{e}; nothing was stored") from None
    created = sum(c for _, c in results)
    log.info(
        "project %s: %d image(s) stored, %d already present", project.id, created, len(results) - created
    )
    if not created:
        response.status_code = status.HTTP_200_OK
    return ImageUploadResult(
        images=[UploadedImage(**ImageOut.model_validate(row).model_dump(), created=c) for row, c in results]
    )


@router.get("", response_model=list[ImageOut])
def list_images(
    project: ProjectDep,
    session: SessionDep,
    image_set: Annotated[ImageSet | None, Query(alias="set", description="Only this set")] = None,
) -> list[ImageOut]:
    return [ImageOut.model_validate(i) for i in crud.list_images(session, project.id, image_set)]


def _image(session: SessionDep, project: Project, image_set: str, filename: str) -> Image:
    image = crud.get_image(session, project.id, image_name(image_set, filename))
    if image is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"image {image_set}/{filename} not found")
    return image


@router.get("/{image_set}/{filename}", response_model=ImageOut)
def get_image(project: ProjectDep, session: SessionDep, image_set: ImageSet, filename: str) -> ImageOut:
    return ImageOut.model_validate(_image(session, project, image_set, filename))


@router.get("/{image_set}/{filename}/download", response_class=StreamingResponse)
def download_image(
    project: ProjectDep, session: SessionDep, storage: StorageDep, image_set: ImageSet, filename: str
) -> StreamingResponse:
    image = _image(session, project, image_set, filename)
    session.close()  # hold no database connection while the bytes flow
    return stream_object(
        storage, image.storage_key, filename, CONTENT_TYPES.get(Path(filename).suffix.lower())
    )


@router.delete("/{image_set}/{filename}", status_code=status.HTTP_204_NO_CONTENT)
def delete_image(
    project: ProjectDep, session: SessionDep, storage: StorageDep, image_set: ImageSet, filename: str
) -> Response:
    """Delete an image and its stored object (its POS row, if any, stays); 409 while a queued or running
    job uses it."""
    image = _image(session, project, image_set, filename)
    crud.check_inputs_free(session, project.id, image.name)  # 409 while a queued or running job uses it
    key = image.storage_key
    session.delete(image)
    session.commit()
    storage.delete(key)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
