"""Request and response models of the REST API."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import AnyHttpUrl, BaseModel, ConfigDict, Field, field_validator

from services.pipeline import JobOptions, Stage

ImageSet = Literal["aerial", "ground"]
WebhookEvent = Literal["job.succeeded", "job.failed"]
DEFAULT_WEBHOOK_EVENTS: tuple[WebhookEvent, ...] = ("job.succeeded", "job.failed")


class Out(BaseModel):
    """Response models read ORM rows directly."""

    model_config = ConfigDict(from_attributes=True)


class In(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# projects
class ProjectCreate(In):
    name: str = Field(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]+$")
    description: str | None = Field(None, max_length=10_000)
    crs: str | None = Field(None, max_length=64, description="CRS of the project's outputs, e.g. EPSG:32633")
    origin: tuple[float, float, float] | None = Field(
        None, description="Local frame origin (lat, lon, h); default: derived from the POS"
    )

    @field_validator("crs")
    @classmethod
    def _known_crs(cls, v: str | None) -> str | None:
        """A CRS pyproj knows (else the job's GIS outputs would fail minutes later)."""
        if v is not None:
            from pyproj import CRS
            from pyproj.exceptions import CRSError

            try:
                CRS.from_user_input(v)
            except CRSError:
                raise ValueError(f"unknown CRS {v!r} (e.g. EPSG:32633)") from None
        return v

    @field_validator("origin")
    @classmethod
    def _origin_on_earth(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is not None:
            lat, lon, h = v
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and -12_000.0 <= h <= 100_000.0):
                raise ValueError(
                    f"origin ({lat}, {lon}, {h}): latitude in [-90, 90], longitude in [-180, 180], "
                    "height in [-12000, 100000] m"
                )
        return v


class ProjectOut(Out):
    id: str
    name: str
    description: str | None
    crs: str | None
    origin_lat: float | None
    origin_lon: float | None
    origin_h: float | None
    created_at: datetime


class ProjectDetail(ProjectOut):
    images: dict[str, int] = Field(description="Number of images per set")
    pos_records: int
    jobs: int


# images
class ImageOut(Out):
    id: str
    name: str
    image_set: str
    sha256: str
    size_bytes: int
    width: int | None
    height: int | None
    created_at: datetime


class UploadedImage(ImageOut):
    created: bool = Field(description="False when the same bytes were already stored under this name")


class ImageUploadResult(BaseModel):
    images: list[UploadedImage]


# multipart uploads
class UploadCreate(In):
    name: str = Field(description="Image name, SET/FILE (e.g. aerial/A0001.jpg)", max_length=512)
    size: int = Field(gt=0, description="Total size in bytes")
    sha256: str | None = Field(None, pattern=r"^[0-9a-fA-F]{64}$", description="Checked on completion")


class UploadOut(BaseModel):
    id: str
    name: str
    size: int
    sha256: str | None
    part_size: int
    part_count: int
    parts_via: Literal["presigned", "api"] = Field(
        description="presigned: PUT parts to the URLs of GET .../parts/{n}; api: PUT them to the API"
    )
    created_at: datetime
    state: Literal["open", "verifying", "rejected"] = Field(
        "open",
        description="open: parts arriving; verifying: assembled, checked in the background; rejected: "
        "the check failed (error; the object deleted; start the upload again)",
    )
    error: str | None = Field(None, description="Why the check rejected it")
    part_urls: list[PartUrl] | None = Field(
        None,
        description="In the answer to the start, with presigned parts (up to 256 of them): where to PUT "
        "each part, so that no GET .../parts/{n} is needed (they expire; GET a part's URL again then)",
    )


class PartUrl(BaseModel):
    part_number: int
    method: Literal["PUT"] = "PUT"
    url: str
    expires_in: int | None = Field(None, description="Seconds the URL stays valid (presigned)")
    needs_auth: bool = Field(description="Whether to send the API key (API route) or not (presigned)")
    size: int = Field(description="Bytes expected in this part")


UploadOut.model_rebuild()


class PartOut(BaseModel):
    part_number: int
    etag: str


class ReceivedPart(BaseModel):
    part_number: int
    size: int
    etag: str = Field(description="Give it back in POST .../complete")
    last_modified: datetime | None = None


class UploadParts(BaseModel):
    id: str
    part_count: int
    parts: list[ReceivedPart] = Field(description="Parts the storage holds, from its list of parts")
    missing: list[int] = Field(description="Part numbers not received yet")
    wrong_size: list[int] = Field(description="Received with another size than planned: send them again")


class CompletedPart(In):
    part_number: int = Field(ge=1, le=10_000)
    etag: str = Field(min_length=1, max_length=200)


class UploadComplete(In):
    parts: list[CompletedPart] | None = Field(
        None,
        min_length=1,
        max_length=10_000,
        description="The parts and their ETags; omitted: the parts the storage lists for this upload",
    )
    sha256: str | None = Field(
        None,
        pattern=r"^[0-9a-fA-F]{64}$",
        description="The file's sha256, when the start did not give it (a client that hashed the file "
        "while its parts travelled); checked like the start's",
    )
    wait: bool = Field(
        True,
        description="true: check the image (sha256, full decode) and register it before answering (201); "
        "false: answer 202 once the parts are assembled, the check running in the background",
    )


# POS
class PosOut(Out):
    image_name: str
    lat: float
    lon: float
    h: float
    attitude: list[list[float]] | None = Field(description="R_world_from_cam (local ENU), 3x3")
    std_xy: float | None
    std_z: float | None
    std_att: float | None
    source_format: str | None


class PosFromExif(In):
    """Which images to read POS from, and how (services.pos.exif)."""

    image_set: ImageSet | None = Field(None, description="Only this set; default: every image")
    names: list[str] | None = Field(
        None, max_length=100_000, description="Only these images (SET/FILE); default: every image"
    )
    altitude: Literal["gps", "relative"] = Field(
        "gps",
        description="gps: the absolute height, EXIF GPSAltitude (else DJI XMP AbsoluteAltitude), above "
        "sea level; relative: DJI XMP RelativeAltitude (above the take-off point) + takeoff_h",
    )
    takeoff_h: float = Field(0.0, ge=-1000, le=10_000, description="Height of the take-off point (relative)")
    attitude: Literal["gimbal", "none"] = Field(
        "gimbal",
        description="gimbal: camera attitude from DJI XMP Gimbal*Degree when present; none: no attitude",
    )
    skip_without_gps: bool = Field(
        False,
        description="Images whose metadata has no position (or no such altitude) are skipped with a "
        "warning instead of rejecting the request (e.g. ground photos without GPS)",
    )


class PosUploadResult(BaseModel):
    format: str
    stored: int = Field(description="Rows inserted or replaced by this upload")
    total: int = Field(description="POS rows of the project after the upload")
    removed: int = Field(0, description="Rows deleted (replace=true)")
    warnings: list[str] = Field(description="E.g. images without a POS row")


# jobs
JOB_KEY_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,127}$"


class JobCreate(In):
    options: JobOptions = Field(default_factory=JobOptions)
    key: str | None = Field(
        None,
        pattern=JOB_KEY_PATTERN,
        description="Idempotency key chosen by the client: a second creation with the same key on the "
        "project returns the first job (200) instead of making another; with other options it is 409",
    )
    campaign_id: str | None = Field(None, max_length=36, description="The campaign the job belongs to")


class JobRerun(In):
    from_stage: Stage | None = Field(None, description="First stage to run again; default: all")
    force: bool = Field(
        False,
        description="Run the stages from from_stage on again even where their inputs and settings are "
        "unchanged (otherwise those are skipped as up to date): their results are computed anew",
    )


class StageRunOut(Out):
    stage: str
    status: str
    attempt: int
    worker: str | None
    node: str | None = Field(None, description="Celery node (NAME@HOST) running the stage")
    heartbeat_at: datetime | None = Field(None, description="Last sign of life of the task running it")
    started_at: datetime
    finished_at: datetime | None
    duration_s: float | None
    error: str | None


class JobOut(Out):
    id: str
    project_id: str
    status: str
    current_stage: str | None
    progress: float = Field(description="0..1")
    progress_percent: float
    progress_message: str | None = Field(None, description="What the running stage last reported")
    options: dict[str, Any]
    timings: dict[str, Any]
    metrics: dict[str, Any]
    outcome: dict[str, Any] | None = Field(
        None,
        description="A succeeded job's registered images per set, result ok or warnings, and the warnings "
        "(ground images not registered ...)",
    )
    error: str | None
    attempt: int
    force_from: str | None = Field(
        None, description="This attempt runs the stages from this one on even where they are up to date"
    )
    key: str | None = Field(None, description="The client's idempotency key")
    campaign_id: str | None = None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobDetail(JobOut):
    stages: list[StageRunOut]


# campaigns
class CampaignCreate(In):
    name: str = Field(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]+$")
    max_concurrent: int = Field(
        2, ge=1, le=1000, description="Jobs of the campaign queued or running at once"
    )


class CampaignJob(BaseModel):
    id: str
    project_id: str
    project_name: str
    key: str | None
    status: str
    current_stage: str | None
    progress_percent: float
    attempt: int
    failed_stage: str | None = Field(description="The stage that failed in the job's latest attempt")
    error: str | None
    registered: dict[str, int] = Field(description="Registered images per set (a succeeded job's outcome)")
    images: dict[str, int]
    result: str | None = Field(description="ok or warnings for a succeeded job")


class CampaignOut(BaseModel):
    id: str
    name: str
    max_concurrent: int
    created_at: datetime
    jobs_by_status: dict[str, int] = Field(description="Number of jobs per status")
    active: int = Field(description="Jobs queued or running")
    ground_registered: int = Field(description="Ground images registered, all succeeded jobs together")
    ground_images: int = Field(description="Ground images of the succeeded jobs")
    done: bool = Field(description="Every job finished (succeeded, failed or cancelled)")


class CampaignDetail(CampaignOut):
    jobs: list[CampaignJob]


class CampaignRetry(In):
    from_failed_stage: bool = Field(
        True, description="Rerun from the stage that failed; false: from the start"
    )
    limit: int | None = Field(
        None,
        ge=0,
        le=1000,
        description="Rerun at most this many (even beyond the free slots); default: the free slots",
    )


class CampaignRetried(BaseModel):
    rerun: list[CampaignJob]
    waiting: list[str] = Field(description="Failed jobs not rerun yet: no free slot (call again later)")


class OptionSpec(BaseModel):
    name: str
    type: str
    default: Any
    defaults: dict[str, Any] = Field(description="The option's default under each profile")
    help: str
    choices: list[Any] | None = None
    minimum: float | None = None
    maximum: float | None = None


class EstimateOut(BaseModel):
    aerial: int
    ground: int
    stages_s: dict[str, float | None] = Field(description="Seconds per stage (None: not measured)")
    total_s: float | None
    relative_error: dict[str, float | None] = Field(
        description="The cost model's leave-one-out relative error on its timed runs (median, max)"
    )


class ProfileOut(BaseModel):
    name: str
    help: str
    options: dict[str, Any] = Field(description="The options this profile sets")
    offered: bool = Field(description="This service's workers run it: a job that names no profile gets it")
    estimate: EstimateOut | None = Field(
        None, description="Its default job's time on a survey of ?aerial=&ground= images (2 CPU cores)"
    )


class OptionsOut(BaseModel):
    profiles: list[ProfileOut]
    options: list[OptionSpec]
    json_schema: dict[str, Any]


# artifacts and matches
class ArtifactOut(Out):
    id: str
    job_id: str
    kind: str
    name: str
    size_bytes: int | None
    sha256: str | None
    content_type: str | None
    created_at: datetime
    download_url: str | None = None


class PairSummary(BaseModel):
    aerial: str
    ground: str
    num_matches: int = Field(description="Putative matches (NIM)")
    num_inliers: int | None = Field(description="The matcher's own verified matches, when stored")


class PairList(BaseModel):
    artifact: str
    method: str
    total: int
    pairs: list[PairSummary]


class PairMatchesOut(PairSummary):
    artifact: str
    aerial_size: tuple[int, int]
    ground_size: tuple[int, int]
    aerial_xy: list[tuple[float, float]] = Field(description="Matched keypoints in the aerial image")
    ground_xy: list[tuple[float, float]] = Field(description="Matched keypoints in the ground image")
    scores: list[float]
    inliers: list[bool] | None
    views: list[str] | None = Field(description="The rendered view each match came through")


# webhooks
class WebhookCreate(In):
    url: AnyHttpUrl
    events: list[WebhookEvent] = Field(default_factory=lambda: list(DEFAULT_WEBHOOK_EVENTS), min_length=1)


class WebhookOut(Out):
    id: str
    url: str
    events: list[str]
    active: bool
    created_at: datetime


class WebhookCreated(WebhookOut):
    secret: str = Field(description="HMAC-SHA256 signing secret; shown only once")


class DeliveryOut(Out):
    id: str
    job_id: str | None
    event: str
    status: str
    attempts: int
    next_attempt_at: datetime | None
    last_error: str | None
    created_at: datetime
