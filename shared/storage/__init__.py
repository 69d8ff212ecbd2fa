"""Object storage: one interface (base.Storage), a local folder or an S3 bucket behind it."""

from __future__ import annotations

from shared.config import Settings, get_settings
from shared.storage.base import (
    NotSupportedError,
    ObjectStat,
    PartStat,
    Storage,
    StorageError,
    StorageKeyError,
)
from shared.storage.keys import InvalidKeyError
from shared.storage.local import LocalStorage
from shared.storage.s3 import S3Storage


def get_storage(settings: Settings | None = None) -> Storage:
    """The storage backend the settings choose (`storage` = local or s3)."""
    s = settings or get_settings()
    if s.storage == "local":
        return LocalStorage(s.storage_root or s.data_dir / "storage")
    if s.storage == "s3":
        return S3Storage(
            s.s3_bucket,
            endpoint_url=s.s3_endpoint_url,
            region=s.s3_region,
            access_key=s.s3_access_key,
            secret_key=s.s3_secret_key,
            public_endpoint_url=s.s3_public_endpoint_url,
            presign_expiry_s=s.s3_presign_expiry_s,
        )
    raise ValueError(f"unknown storage backend {s.storage!r} (expected local or s3)")


__all__ = [
    "InvalidKeyError",
    "LocalStorage",
    "NotSupportedError",
    "ObjectStat",
    "PartStat",
    "S3Storage",
    "Storage",
    "StorageError",
    "StorageKeyError",
    "get_storage",
]
