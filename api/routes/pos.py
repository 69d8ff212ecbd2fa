"""POS (position and orientation) of a project's images: upload a file, read back the rows."""

from __future__ import annotations

import logging
from typing import Annotated

import sqlalchemy as sa
from fastapi import APIRouter, File, HTTPException, Query, UploadFile, status

from api.deps import ProjectDep, SessionDep, SettingsDep
from api.errors import pos_error_detail
from api.posfile import PosFormat, check_against_project, detect_format, parse_pos_text
from api.schemas import PosOut, PosUploadResult
from services.pos import PosError
from shared.db import crud
from shared.db.models import PosRecordRow

router = APIRouter(prefix="/projects/{project_id}/pos", tags=["pos"])
log = logging.getLogger("midview.api")


def _unprocessable(message: str, errors: list[str]) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, {"message": message, "errors": errors})


@router.post(
    "",
    response_model=PosUploadResult,
    responses={422: {"description": "Bad rows, or rows naming no uploaded image; nothing stored"}},
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
    row) and leave the stored POS untouched; images without a row are only reported as warnings."""
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
    removed = 0
    if replace:
        removed = session.execute(
            sa.delete(PosRecordRow).where(
                PosRecordRow.project_id == project.id, PosRecordRow.image_name.not_in(names_in_file)
            )
        ).rowcount
    try:
        stored = crud.add_pos_records(session, project.id, records, source_format=fmt)
    except ValueError as e:
        session.rollback()
        raise _unprocessable("invalid POS", [str(e)]) from None
    session.commit()
    total = len(crud.list_pos_records(session, project.id))
    log.info("project %s: %d POS rows stored from %s (%s)", project.id, stored, source, fmt)
    return PosUploadResult(
        format=fmt, stored=stored, total=total, removed=removed or 0, warnings=check.warnings
    )


@router.get("", response_model=list[PosOut])
def list_pos(project: ProjectDep, session: SessionDep) -> list[PosOut]:
    return [PosOut.model_validate(r) for r in crud.list_pos_records(session, project.id)]
