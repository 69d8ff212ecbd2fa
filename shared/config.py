"""Settings in one place: defaults, overridden by MIDVIEW_* environment variables or a .env file."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="MIDVIEW_", env_file=".env", extra="ignore")

    data_dir: Path = Field(Path("runs"), description="Working folder of the CLI and the embedded service")
    log_level: str = Field("INFO", description="Logging level: DEBUG, INFO, WARNING, ERROR")
    log_json: bool = Field(False, description="Log one JSON object per line instead of text")
    device: str = Field("auto", description="Torch device for learned features: auto, cpu or cuda")
    num_threads: int = Field(0, description="Torch/numba threads; 0 uses every core")

    # state and storage (shared/db, shared/storage)
    database_url: str = Field("", description="SQLAlchemy URL; empty uses sqlite:///DATA_DIR/midview.db")
    api_key_pepper: str = Field("", description="HMAC secret for API key hashes; empty: plain SHA-256")
    storage: Literal["local", "s3"] = Field("local", description="Object storage backend: local or s3")
    storage_root: Path | None = Field(None, description="Local storage folder; default DATA_DIR/storage")
    s3_endpoint_url: str | None = Field(None, description="S3 endpoint (SeaweedFS, MinIO); None for AWS")
    s3_public_endpoint_url: str | None = Field(
        None, description="Endpoint clients use for presigned URLs, when it differs from s3_endpoint_url"
    )
    s3_bucket: str = Field("midview", description="S3 bucket holding every object")
    s3_region: str = Field("us-east-1", description="S3 region (also used to sign requests)")
    s3_access_key: str | None = Field(None, description="S3 access key; None uses the boto3 default chain")
    s3_secret_key: str | None = Field(None, description="S3 secret key")
    s3_presign_expiry_s: int = Field(3600, ge=1, le=7 * 24 * 3600, description="Lifetime of presigned URLs")

    # workers (workers/)
    dispatcher: str = Field(
        "embedded",
        description="How jobs reach the workers: embedded (a thread of the API process) or celery",
    )
    public_base_url: str = Field(
        "",
        description="The API's public URL (https://midview.example.com): prefixes the result links of "
        "webhook payloads; empty: links relative to the API root",
    )
    webhook_allow_networks: str = Field(
        "",
        description="CIDR networks (comma-separated) that webhooks may reach although they are not public "
        "(loopback, private, link-local ...); empty: public addresses only",
    )
    broker_url: str = Field("redis://127.0.0.1:6379/0", description="Celery broker (Redis) URL")
    result_backend: str = Field("", description="Celery result backend URL; empty: the broker URL")
    work_dir: Path | None = Field(None, description="Workers' local job folders; default DATA_DIR/work")
    stall_timeout_s: float = Field(
        900.0, gt=0, description="A job without progress for this long and no live task is re-dispatched"
    )
    task_max_retries: int = Field(
        5, ge=0, description="Retries of a task after a transient error (storage, database, broker)"
    )
    heartbeat_every_s: float = Field(
        10.0, gt=0, description="How often a running task refreshes its heartbeat (Redis key, stage run)"
    )
    reconcile_every_s: float = Field(
        15.0, gt=0, description="How often celery beat sends the reconcile task (stalled or lost stages)"
    )
    heartbeat_timeout_s: float = Field(
        30.0,
        gt=0,
        description="A running stage whose heartbeat is older than this is re-dispatched when its Celery "
        "node does not answer a ping (the node died) or when the broker holds no task or message of its job "
        "(the broker lost them)",
    )
    heartbeat_dead_s: float = Field(
        1800.0,
        gt=0,
        description="A running stage whose heartbeat is older than this is re-dispatched even when its "
        "node answers (the node restarted, or the task hangs)",
    )

    @model_validator(mode="after")
    def _derive_paths(self) -> Settings:
        """Fill the defaults that live under data_dir."""
        if not self.database_url:
            self.database_url = f"sqlite:///{(self.data_dir / 'midview.db').as_posix()}"
        if self.storage_root is None:
            self.storage_root = self.data_dir / "storage"
        if not self.result_backend:
            self.result_backend = self.broker_url
        if self.work_dir is None:
            self.work_dir = self.data_dir / "work"
        return self


@lru_cache
def get_settings() -> Settings:
    return Settings()
