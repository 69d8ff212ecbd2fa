"""POS (position and orientation) of a project's images: upload a file, or read it from the stored
images' EXIF/XMP; read back the rows."""

from __future__ import annotations

import logging
from typing import Annotated

import sqlalchemy as sa
from fastapi import APIRouter, File, HTTPException, Query, UploadFile, status
from sqlalchemy.orm import Session

from api.deps import ProjectDep, SessionDep, SettingsDep, StorageDep
from api.errors import pos_error_detail
from api.posfile import PosFormat, check_against_project, detect_format, parse_pos_text, pos_from_images
from api.schemas import PosFromExif, PosOut, PosUploadResult
from services.pos import PosError
from shared.db import crud
from shared.db.models import PosRecordRow, Project

router = APIRouter(prefix="/projects/{project_id}/pos", tags=["pos"])
log = logging.getLogger("midview.api")


def _unprocessable(message: str, errors: list[str]) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, {"message": message, "errors": errors})


@router.post(
    "",
    response_model=PosUploadResult,
    responses={
        409: {"description": "A queued or running job uses the project's POS"},
        422: {"description": "Bad rows, or rows naming no uploaded image; nothing stored"},
    },
)
def upload_pos(
    project: ProjectDep,
    session: SessionDep,
    settings: SettingsDep,
    file: Annotated[UploadFile, File(description="POS file: midview CSV, ODM geo.txt or JSON")],
    format: Annotated[
        PosFormat, Query(description="File format; auto: from the name, else the content")
    ] = "auto",
    replace: Annotated[bool, Query(description="Delete stored rows that this file does not name")] = False,
) -> PosUploadResult:
    """Parse and validate a POS file against the project's images, then insert or replace its rows by
    image name. Bad rows, or rows naming no uploaded image, reject the whole file (422, one message per
    row) and leave the stored POS untouched; images without a row are only reported as warnings. While
    a queued or running job uses the POS, a file that would change it is 409 (the same rows again: 200)."""
    data = file.file.read(settings.max_pos_bytes + 1)
    if len(data) > settings.max_pos_bytes:
        raise HTTPException(
            status.HTTP_413_CONTENT_TOO_LARGE, f"POS file larger than {settings.max_pos_bytes} bytes"
        )
    source = file.filename or "pos"
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise _unprocessable("invalid POS", [f"{source}: not UTF-8 text ({e})"]) from None
    fmt = detect_format(text, file.filename) if format == "auto" else format
    try:
        records = parse_pos_text(text, fmt, source)
    except PosError as e:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, pos_error_detail(e)) from None
    images = [i.name for i in crud.list_images(session, project.id)]
    kept = [] if replace else [r.image_name for r in crud.list_pos_records(session, project.id)]
    check = check_against_project(records, images, kept)
    if check.errors:
        raise _unprocessable("POS rows name images that are not uploaded", check.errors)
    names_in_file = {r.name for r in records}  # after bare names were matched to the images
    before = crud.pos_digest(session, project.id)
    removed = 0
    if replace:
        deleted = session.execute(
            sa.delete(PosRecordRow).where(
                PosRecordRow.project_id == project.id, PosRecordRow.image_name.not_in(names_in_file)
            )
        )
        removed = getattr(deleted, "rowcount", 0)  # a DELETE's CursorResult
    try:
        stored = crud.add_pos_records(session, project.id, records, source_format=fmt)
    except ValueError as e:
        session.rollback()
        raise _unprocessable("invalid POS", [str(e)]) from None
    if crud.pos_digest(session, project.id) != before:
        try:
            crud.check_inputs_free(session, project.id)  # 409 while a queued or running job uses the POS
        except crud.ConflictError:
            session.rollback()
            raise
    session.commit()
    total = len(crud.list_pos_records(session, project.id))
    log.info("project %s: %d POS rows stored from %s (%s)", project.id, stored, source, fmt)
    return PosUploadResult(
        format=fmt, stored=stored, total=total, removed=removed or 0, warnings=check.warnings
    )


def _exif_images(session: Session, project: Project, body: PosFromExif) -> list[tuple[str, str]]:
    """[(name, storage key)] of the images to read: the set's, or those named; 422 for unknown names."""
    images = crud.list_images(session, project.id, body.image_set)
    if body.names is not None:
        by_name = {im.name: im for im in images}
        unknown = [n for n in body.names if n not in by_name]
        if unknown:
            raise _unprocessable(
                "names that are no uploaded image"
                + (f" of the {body.image_set} set" if body.image_set else ""),
                [f"image {n!r} is not uploaded" for n in unknown[:100]],
            )
        images = [by_name[n] for n in dict.fromkeys(body.names)]
    if not images:
        raise _unprocessable("no images to read POS from", ["the project has no such images"])
    return [(im.name, im.storage_key) for im in images]


@router.post(
    "/from-exif",
    response_model=PosUploadResult,
    responses={422: {"description": "An image is unreadable or has no position; nothing stored"}},
)
def pos_from_exif(
    body: PosFromExif, project: ProjectDep, session: SessionDep, storage: StorageDep, settings: SettingsDep
) -> PosUploadResult:
    """Read POS from the stored images' EXIF GPS and DJI XMP (drone-dji: altitudes, gimbal attitude, RTK
    accuracies) and insert or replace their rows (`source_format` exif). Any image that cannot be read,
    or has no position or no altitude of the kind asked for, rejects the request (422, one reason per
    image) and leaves the stored POS untouched; with `skip_without_gps` images without a position are
    skipped with a warning instead."""
    crud.check_inputs_free(session, project.id)  # 409 while a queued or running job uses the POS
    images = _exif_images(session, project, body)
    session.commit()  # no database connection held while the images download
    options = {"altitude": body.altitude, "attitude": body.attitude, "takeoff_h": body.takeoff_h}
    result = pos_from_images(storage, images, options, body.skip_without_gps, settings.upload_tmp_dir)
    if result.errors:
        raise _unprocessable("POS could not be read from every image; nothing stored", result.errors)
    if not result.records:
        raise _unprocessable("no image carries a position; nothing stored", result.warnings)
    try:
        stored = crud.add_pos_records(session, project.id, result.records, source_format="exif")
    except ValueError as e:
        session.rollback()
        raise _unprocessable("invalid POS", [str(e)]) from None
    session.commit()
    total = len(crud.list_pos_records(session, project.id))
    log.info("project %s: %d POS rows read from EXIF/XMP (%s altitude)", project.id, stored, body.altitude)
    return PosUploadResult(format="exif", stored=stored, total=total, removed=0, warnings=result.warnings)


@router.get("", response_model=list[PosOut])
def list_pos(project: ProjectDep, session: SessionDep) -> list[PosOut]:
    return [PosOut.model_validate(r) for r in crud.list_pos_records(session, project.id)]
