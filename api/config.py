"""Settings of the API process: shared.config.Settings plus what only the API reads (MIDVIEW_* as well)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_validator

from shared.config import Settings
from shared.db.crud import API_KEY_PREFIX

MB = 1024 * 1024


class ApiSettings(Settings):
    bootstrap_api_key: str | None = Field(
        None,
        description="An API key (mv_...) created at startup for bootstrap_tenant if missing; "
        "for the embedded single-user setup",
    )
    bootstrap_tenant: str = Field("default", description="Tenant owning bootstrap_api_key")
    migrate_on_startup: bool = Field(False, description="Apply database migrations when the API starts")

    max_upload_bytes: int = Field(512 * MB, ge=1, description="Largest image accepted, in bytes")
    max_image_pixels_aerial: int = Field(
        200_000_000,
        ge=1,
        description="Largest aerial image accepted, in pixels (width x height, read from the file's header "
        "before anything is decoded: a few KB can claim gigapixels); the default fits 100 MP survey cameras",
    )
    max_image_pixels_ground: int = Field(
        200_000_000, ge=1, description="Largest ground image accepted, in pixels (as max_image_pixels_aerial)"
    )
    upload_expiry_h: float = Field(
        24.0,
        gt=0,
        description="A resumable upload still open this many hours after it started is aborted"
        " (its parts deleted from the storage)",
    )
    max_concurrent_per_key: int = Field(
        24,
        ge=1,
        description="Requests of one API key in flight at once in each API process; one more is answered "
        "429 before it takes a database connection (a burst from one key cannot starve other tenants)",
    )
    max_header_bytes: int = Field(
        64 * 1024,
        ge=8 * 1024,
        le=16 * MB,
        description="Largest request line and headers together, in bytes; more is answered 400 and the "
        "connection closed before anything is parsed further (uvicorn's h11 parser, server_options)",
    )
    max_files_per_request: int = Field(1000, ge=1, description="Most files in one upload request")
    max_pos_bytes: int = Field(64 * MB, ge=1, description="Largest POS file accepted, in bytes")
    max_json_bytes: int = Field(1 * MB, ge=1024, description="Largest JSON request body, in bytes")
    max_request_bytes: int = Field(
        2048 * MB,
        ge=1,
        description="Largest multipart image upload request, in bytes (larger sets: the uploads API)",
    )
    body_read_timeout_s: float = Field(
        30.0, gt=0, description="A request whose body stops arriving for this long is answered 408"
    )
    max_validation_errors: int = Field(20, ge=1, description="Validation errors listed in a 422 at most")
    db_pool_size: int = Field(
        10,
        ge=1,
        le=200,
        description="Database connections each API process keeps open (as many more for bursts); status "
        "reads and key lookups run at most this many at once, so they never wait on a new connection",
    )
    verify_workers: int = Field(
        1, ge=1, le=16, description="Threads checking uploads completed with wait false (full decode)"
    )
    verify_sweep_s: float = Field(
        30.0, gt=0, description="How often uploads left verifying (an API process died) are checked again"
    )
    status_cache_s: float = Field(
        0.5,
        ge=0,
        le=10,
        description="GET /jobs/{id} answers are reused this long by each API process (what workers wrote "
        "shows within this time; cancel and rerun here at once); 0: read the database every time",
    )
    auth_cache_s: float = Field(
        5.0,
        ge=0,
        description="API keys that authenticated are remembered this long by each API process (a key "
        "revoked elsewhere stops working within this time); 0: ask the database on every request",
    )
    rate_limit_per_minute: int = Field(
        1200, ge=0, description="Requests a minute per API key (429 with Retry-After past it); 0: no limit"
    )
    rate_limit_burst: int = Field(200, ge=1, description="Requests at once per API key (in-process limiter)")
    rate_limit_backend: Literal["auto", "memory", "redis"] = Field(
        "auto",
        description="Where the counts live: redis (the broker's Redis, shared by every API process), "
        "memory (this process); auto: redis with the Celery dispatcher",
    )
    upload_part_size: int = Field(
        8 * MB, ge=5 * MB, description="Part size of multipart uploads (S3 needs >= 5 MiB)"
    )
    upload_tmp_dir: str | None = Field(None, description="Folder for upload temp files; default: system")
    cache_dir: str | None = Field(None, description="Cache of downloaded artifacts; default DATA_DIR/cache")
    events_poll_s: float = Field(0.5, gt=0, le=10, description="Job event stream: database poll period")
    events_heartbeat_s: float = Field(15.0, gt=0, description="Job event stream: keep-alive comment period")
    readyz_timeout_s: float = Field(5.0, gt=0, description="Readiness probe: time allowed to each check")

    @property
    def max_image_pixels(self) -> dict[str, int]:
        """The pixel limit of each image set."""
        return {"aerial": self.max_image_pixels_aerial, "ground": self.max_image_pixels_ground}

    @field_validator("bootstrap_api_key")
    @classmethod
    def _key_shape(cls, value: str | None) -> str | None:
        if value is not None and (not value.startswith(API_KEY_PREFIX) or len(value) < 20):
            raise ValueError(
                f"bootstrap_api_key must start with {API_KEY_PREFIX!r} and have >= 20 characters"
            )
        return value or None


def server_options(settings: ApiSettings) -> dict[str, Any]:
    """uvicorn's options for the API (uvicorn.run(app, **server_options(s)); the Dockerfile passes the
    same as flags): the h11 parser, which bounds the request head (httptools does not bound it)."""
    return {"http": "h11", "h11_max_incomplete_event_size": settings.max_header_bytes}


def server_flags(settings: ApiSettings) -> list[str]:
    """server_options as `uvicorn` command-line flags."""
    return ["--http", "h11", "--h11-max-incomplete-event-size", str(settings.max_header_bytes)]
