"""The object storage interface shared by the local and S3 backends."""

from __future__ import annotations

import abc
import builtins
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import BinaryIO

MIN_PART_NUMBER, MAX_PART_NUMBER = 1, 10_000


class StorageError(Exception):
    """A storage operation failed."""


class StorageKeyError(StorageError, KeyError):
    """The object (or multipart upload) does not exist."""

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0]) if self.args else "missing key"


class NotSupportedError(StorageError, NotImplementedError):
    """The backend cannot do this operation."""


@dataclass(frozen=True)
class ObjectStat:
    key: str
    size: int
    etag: str  # without quotes; S3 multipart objects end with "-<parts>"
    last_modified: datetime | None = None
    content_type: str | None = None


@dataclass(frozen=True)
class PartStat:
    """One part received by an unfinished multipart upload."""

    part_number: int
    size: int
    etag: str  # without quotes, as complete_multipart wants it
    last_modified: datetime | None = None


def check_part_number(part_number: int) -> int:
    if not MIN_PART_NUMBER <= int(part_number) <= MAX_PART_NUMBER:
        raise ValueError(f"part number {part_number} outside [{MIN_PART_NUMBER}, {MAX_PART_NUMBER}]")
    return int(part_number)


class Storage(abc.ABC):
    """Objects addressed by keys (see keys.py). Writes replace whole objects; readers never see a partial
    object. Missing objects raise StorageKeyError; unsafe keys raise keys.InvalidKeyError."""

    # objects
    @abc.abstractmethod
    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectStat:
        """Store data under key."""

    @abc.abstractmethod
    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectStat:
        """Store a local file, streamed (S3: multipart above the backend's threshold)."""

    @abc.abstractmethod
    def put_stream(self, key: str, fileobj: BinaryIO, content_type: str | None = None) -> ObjectStat:
        """Store everything readable from a binary file object, streamed."""

    @abc.abstractmethod
    def get_bytes(self, key: str) -> bytes:
        """The whole object in memory."""

    @abc.abstractmethod
    def download(self, key: str, path: str | Path) -> Path:
        """Copy the object to a local file (written atomically); return the path."""

    @abc.abstractmethod
    def open_read(self, key: str) -> BinaryIO:
        """A readable binary stream of the object; close it (or use `with`)."""

    @abc.abstractmethod
    def exists(self, key: str) -> bool:
        """Whether the object exists."""

    @abc.abstractmethod
    def stat(self, key: str) -> ObjectStat:
        """Size and ETag of the object."""

    @abc.abstractmethod
    def list(self, prefix: str = "") -> list[str]:
        """Sorted keys starting with prefix (a plain string prefix, as in S3)."""

    @abc.abstractmethod
    def delete(self, key: str) -> None:
        """Delete the object; deleting a missing object is not an error (as in S3)."""

    @abc.abstractmethod
    def delete_prefix(self, prefix: str) -> int:
        """Delete every object under a non-empty prefix; return how many were deleted."""

    # URLs
    @abc.abstractmethod
    def presigned_get_url(self, key: str, expires_s: int | None = None) -> str | None:
        """A URL that downloads the object without credentials for expires_s seconds.

        S3: a presigned HTTP URL (not checked for existence). Local: a `file://` URL, only useful on the
        same machine; the API should stream the object itself instead of redirecting to it."""

    # multipart uploads driven by a client
    @abc.abstractmethod
    def create_multipart(self, key: str, content_type: str | None = None) -> str:
        """Start a multipart upload to key; return its upload id."""

    @abc.abstractmethod
    def presigned_part_url(
        self,
        key: str,
        upload_id: str,
        part_number: int,
        expires_s: int | None = None,
        size: int | None = None,
    ) -> str | None:
        """A URL the client PUTs one part to (the response ETag header is the part's ETag); with `size`,
        the part's length is signed into it (the storage refuses a PUT of any other length).

        None when the backend has no such URL (local): the API then receives the part and calls
        upload_part itself."""

    @abc.abstractmethod
    def upload_part(self, key: str, upload_id: str, part_number: int, data: bytes | BinaryIO) -> str:
        """Upload one part through this process; return its ETag."""

    @abc.abstractmethod
    def list_parts(
        self, key: str, upload_id: str, etags: Mapping[int, str] | None = None
    ) -> builtins.list[PartStat]:
        """The parts an unfinished upload has received so far, one per part number (a client that lost
        its ETags resumes from them): the newest, or the one whose ETag `etags` names for its number
        where a part was sent more than once; StorageKeyError when the upload does not exist."""

    @abc.abstractmethod
    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> ObjectStat:
        """Assemble the parts [(part_number, etag), ...] into the object."""

    @abc.abstractmethod
    def abort_multipart(self, key: str, upload_id: str) -> None:
        """Drop an unfinished upload and its parts."""
