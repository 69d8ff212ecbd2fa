"""Camera intrinsics of a project, per image set (docs/formats.md, cameras.json).

Images without EXIF focal lengths (synthetic surveys, stripped exports) need them for the aerial SfM;
the workers read the stored object when they prepare a job.
"""

from __future__ import annotations

import json
from typing import Literal

from fastapi import APIRouter, HTTPException, status
from pydantic import BaseModel, ConfigDict, Field, model_validator

from api.deps import ProjectDep, SessionDep, StorageDep
from shared.db import crud
from shared.storage import StorageKeyError
from shared.storage.keys import cameras_key

router = APIRouter(prefix="/projects/{project_id}/cameras", tags=["cameras"])

# COLMAP camera models and their parameter counts
PARAM_COUNTS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}


class CameraIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]
    width: int = Field(gt=0, le=100_000)
    height: int = Field(gt=0, le=100_000)
    params: list[float]

    @model_validator(mode="after")
    def _params(self) -> CameraIn:
        n = PARAM_COUNTS[self.model]
        if len(self.params) != n:
            raise ValueError(f"{self.model} takes {n} params, got {len(self.params)}")
        if self.params[0] <= 0 or (self.model in ("PINHOLE", "OPENCV") and self.params[1] <= 0):
            raise ValueError("focal lengths must be positive")
        return self


class CamerasIn(BaseModel):
    """Intrinsics per image set: {"aerial": {...}, "ground": {...}}; either may be left out."""

    model_config = ConfigDict(extra="forbid")

    aerial: CameraIn | None = None
    ground: CameraIn | None = None


@router.put("", response_model=CamerasIn, response_model_exclude_none=True)
def put_cameras(body: CamerasIn, project: ProjectDep, storage: StorageDep, session: SessionDep) -> CamerasIn:
    """Store (replace) the project's intrinsics. Unknown models, wrong parameter counts or sizes: 422;
    409 while a queued or running job uses them (unless they are the stored ones)."""
    data = body.model_dump(exclude_none=True)
    if not data:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "give intrinsics for aerial and/or ground")
    key = cameras_key(project.tenant_id, project.id)
    try:
        unchanged = json.loads(storage.get_bytes(key)) == json.loads(json.dumps(data))
    except (StorageKeyError, ValueError):
        unchanged = False
    if unchanged:
        return body
    crud.check_inputs_free(session, project.id)
    storage.put_bytes(
        cameras_key(project.tenant_id, project.id), json.dumps(data, indent=1).encode(), "application/json"
    )
    return body


@router.get("", response_model=CamerasIn, response_model_exclude_none=True)
def get_cameras(project: ProjectDep, storage: StorageDep) -> CamerasIn:
    """The stored intrinsics; 404 when none were given (the SfM then uses EXIF)."""
    key = cameras_key(project.tenant_id, project.id)
    if not storage.exists(key):
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no camera intrinsics stored for this project")
    return CamerasIn.model_validate_json(storage.get_bytes(key))
