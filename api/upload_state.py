"""State of client-driven multipart uploads, kept as small JSON objects in storage under the project
(`.../projects/{p}/uploads/{id}.json`) since the database has no table for them; deleting the project
deletes them with everything else under its prefix."""

from __future__ import annotations

import json
import math
import re
import uuid
from datetime import datetime

from pydantic import BaseModel

from shared.storage import Storage, StorageKeyError
from shared.storage.base import MAX_PART_NUMBER
from shared.storage.keys import project_prefix

UPLOAD_ID_RE = re.compile(r"^[0-9a-f]{32}$")


class UploadState(BaseModel):
    id: str
    name: str  # image name, aerial/A0001.jpg
    key: str  # where the parts are assembled: the image's final key
    storage_upload_id: str
    size: int
    sha256: str | None
    part_size: int
    part_count: int
    created_at: datetime


def plan_parts(size: int, part_size: int) -> tuple[int, int]:
    """(part size, part count) for size bytes: part_size, grown when it would need more than 10000 parts."""
    part_size = max(part_size, math.ceil(size / MAX_PART_NUMBER))
    return part_size, max(1, math.ceil(size / part_size))


def new_upload_id() -> str:
    return uuid.uuid4().hex


def _prefix(tenant_id: str, project_id: str) -> str:
    return f"{project_prefix(tenant_id, project_id)}uploads/"


def state_key(tenant_id: str, project_id: str, upload_id: str) -> str:
    if not UPLOAD_ID_RE.match(upload_id):
        raise StorageKeyError(f"upload {upload_id} not found")
    return f"{_prefix(tenant_id, project_id)}{upload_id}.json"


def save(storage: Storage, tenant_id: str, project_id: str, state: UploadState) -> None:
    storage.put_bytes(
        state_key(tenant_id, project_id, state.id),
        state.model_dump_json().encode(),
        content_type="application/json",
    )


def load(storage: Storage, tenant_id: str, project_id: str, upload_id: str) -> UploadState:
    """The state of an upload; StorageKeyError when unknown (finished, aborted or never created)."""
    return UploadState.model_validate(
        json.loads(storage.get_bytes(state_key(tenant_id, project_id, upload_id)))
    )


def delete(storage: Storage, tenant_id: str, project_id: str, upload_id: str) -> None:
    storage.delete(state_key(tenant_id, project_id, upload_id))


def list_uploads(storage: Storage, tenant_id: str, project_id: str) -> list[UploadState]:
    """Unfinished uploads of the project, oldest first."""
    out = []
    for key in storage.list(_prefix(tenant_id, project_id)):
        if key.endswith(".json"):
            try:
                out.append(UploadState.model_validate(json.loads(storage.get_bytes(key))))
            except StorageKeyError:  # finished meanwhile
                continue
    return sorted(out, key=lambda s: s.created_at)


def active_for_names(storage: Storage, tenant_id: str, project_id: str, names: set[str]) -> list[str]:
    """Those of names that an unfinished multipart upload is writing."""
    return sorted({s.name for s in list_uploads(storage, tenant_id, project_id)} & names)
