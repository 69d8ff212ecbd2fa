"""Objects in an S3 bucket (AWS, SeaweedFS, MinIO, ...) through boto3."""

from __future__ import annotations

import builtins
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO

import boto3
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

from shared.storage.base import (
    ObjectStat,
    PartStat,
    Storage,
    StorageError,
    StorageKeyError,
    check_part_number,
)
from shared.storage.keys import validate_key, validate_prefix

MB = 1024 * 1024
MISSING_CODES = {"404", "NoSuchKey", "NotFound", "NoSuchUpload"}


@contextmanager
def _errors(what: str) -> Iterator[None]:
    """Turn botocore errors into StorageKeyError (missing) or StorageError."""
    try:
        yield
    except ClientError as e:
        code = str(e.response.get("Error", {}).get("Code", ""))
        if code in MISSING_CODES:
            raise StorageKeyError(f"{what}: not found ({code})") from e
        raise StorageError(f"{what}: {e}") from e
    except BotoCoreError as e:
        raise StorageError(f"{what}: {e}") from e


def _stamp(part: PartStat) -> float:
    return part.last_modified.timestamp() if part.last_modified is not None else 0.0


def _chosen(versions: list[PartStat], etag: str | None) -> PartStat:
    """The send of one part number with `etag`, else the newest (the later listed on a tie)."""
    order = range(len(versions))
    return versions[max(order, key=lambda i: (versions[i].etag == etag, _stamp(versions[i]), i))]


class S3Storage(Storage):
    """Storage in one S3 bucket.

    public_endpoint_url: the endpoint clients reach when it differs from the one this process uses
    (e.g. `http://seaweedfs:8333` inside compose, `https://s3.example.com` outside); presigned URLs
    are signed for it. Files above multipart_threshold are uploaded in multipart_chunksize parts.
    """

    def __init__(
        self,
        bucket: str,
        *,
        endpoint_url: str | None = None,
        region: str = "us-east-1",
        access_key: str | None = None,
        secret_key: str | None = None,
        public_endpoint_url: str | None = None,
        presign_expiry_s: int = 3600,
        multipart_threshold: int = 16 * MB,
        multipart_chunksize: int = 8 * MB,
        max_concurrency: int = 4,
    ) -> None:
        self.bucket = bucket
        self.presign_expiry_s = presign_expiry_s
        self.transfer = TransferConfig(
            multipart_threshold=multipart_threshold,
            multipart_chunksize=multipart_chunksize,
            max_concurrency=max_concurrency,
        )
        self.client = self._client(endpoint_url, region, access_key, secret_key)
        self._presigner = (
            self._client(public_endpoint_url, region, access_key, secret_key)
            if public_endpoint_url
            else self.client
        )

    @staticmethod
    def _client(endpoint_url: str | None, region: str, access_key: str | None, secret_key: str | None) -> Any:
        config = Config(
            signature_version="s3v4",
            s3={"addressing_style": "path" if endpoint_url else "auto"},
            retries={"max_attempts": 5, "mode": "standard"},
            # S3-compatible servers differ in their support of the newer default checksums
            request_checksum_calculation="when_required",
            response_checksum_validation="when_required",
        )
        return boto3.session.Session().client(
            "s3",
            endpoint_url=endpoint_url,
            region_name=region,
            aws_access_key_id=access_key,
            aws_secret_access_key=secret_key,
            config=config,
        )

    def __repr__(self) -> str:
        return f"S3Storage(bucket={self.bucket!r}, endpoint={self.client.meta.endpoint_url!r})"

    def ensure_bucket(self) -> None:
        """Create the bucket if it does not exist yet."""
        try:
            self.client.head_bucket(Bucket=self.bucket)
            return
        except ClientError as e:
            if str(e.response.get("Error", {}).get("Code")) not in {"404", "NoSuchBucket", "NotFound"}:
                raise StorageError(f"bucket {self.bucket!r}: {e}") from e
        with _errors(f"create bucket {self.bucket!r}"):
            self.client.create_bucket(Bucket=self.bucket)

    @staticmethod
    def _extra(content_type: str | None) -> dict[str, str]:
        return {"ContentType": content_type} if content_type else {}

    # objects
    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectStat:
        validate_key(key)
        with _errors(f"put {key!r}"):
            r = self.client.put_object(Bucket=self.bucket, Key=key, Body=data, **self._extra(content_type))
        return ObjectStat(key=key, size=len(data), etag=r["ETag"].strip('"'), content_type=content_type)

    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectStat:
        validate_key(key)
        with _errors(f"upload {str(path)!r} to {key!r}"):
            self.client.upload_file(
                str(path), self.bucket, key, ExtraArgs=self._extra(content_type), Config=self.transfer
            )
        return self.stat(key)

    def put_stream(self, key: str, fileobj: BinaryIO, content_type: str | None = None) -> ObjectStat:
        validate_key(key)
        with _errors(f"upload stream to {key!r}"):
            self.client.upload_fileobj(
                fileobj, self.bucket, key, ExtraArgs=self._extra(content_type), Config=self.transfer
            )
        return self.stat(key)

    def get_bytes(self, key: str) -> bytes:
        with self.open_read(key) as body:
            return body.read()

    def download(self, key: str, path: str | Path) -> Path:
        validate_key(key)
        dest = Path(path)
        dest.parent.mkdir(parents=True, exist_ok=True)
        with _errors(f"download {key!r}"):  # boto3 writes a temporary file and renames it
            self.client.download_file(self.bucket, key, str(dest), Config=self.transfer)
        return dest

    def open_read(self, key: str) -> BinaryIO:
        validate_key(key)
        with _errors(f"get {key!r}"):
            return self.client.get_object(Bucket=self.bucket, Key=key)["Body"]

    def exists(self, key: str) -> bool:
        try:
            self.stat(key)
        except StorageKeyError:
            return False
        return True

    def stat(self, key: str) -> ObjectStat:
        validate_key(key)
        with _errors(f"stat {key!r}"):
            r = self.client.head_object(Bucket=self.bucket, Key=key)
        return ObjectStat(
            key=key,
            size=int(r["ContentLength"]),
            etag=r["ETag"].strip('"'),
            last_modified=r.get("LastModified"),
            content_type=r.get("ContentType"),
        )

    def _iter_keys(self, prefix: str) -> Iterator[str]:
        pages = self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix)
        with _errors(f"list {prefix!r}"):
            for page in pages:
                for obj in page.get("Contents", []):
                    yield obj["Key"]

    def list(self, prefix: str = "") -> list[str]:
        validate_prefix(prefix)
        return sorted(self._iter_keys(prefix))

    def delete(self, key: str) -> None:
        validate_key(key)
        with _errors(f"delete {key!r}"):
            self.client.delete_object(Bucket=self.bucket, Key=key)

    def delete_prefix(self, prefix: str) -> int:
        if not validate_prefix(prefix):
            raise ValueError("delete_prefix needs a non-empty prefix")
        keys = self.list(prefix)
        for i in range(0, len(keys), 1000):
            batch = [{"Key": k} for k in keys[i : i + 1000]]
            with _errors(f"delete {prefix!r}*"):
                r = self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})
            if r.get("Errors"):
                raise StorageError(f"delete {prefix!r}*: {r['Errors'][:3]}")
        return len(keys)

    # URLs
    def presigned_get_url(self, key: str, expires_s: int | None = None) -> str | None:
        validate_key(key)
        return self._presigner.generate_presigned_url(
            "get_object",
            Params={"Bucket": self.bucket, "Key": key},
            ExpiresIn=expires_s or self.presign_expiry_s,
        )

    # multipart
    def create_multipart(self, key: str, content_type: str | None = None) -> str:
        validate_key(key)
        with _errors(f"create multipart upload {key!r}"):
            r = self.client.create_multipart_upload(Bucket=self.bucket, Key=key, **self._extra(content_type))
        return r["UploadId"]

    def presigned_part_url(
        self,
        key: str,
        upload_id: str,
        part_number: int,
        expires_s: int | None = None,
        size: int | None = None,
    ) -> str | None:
        validate_key(key)
        params: dict = {"Bucket": self.bucket, "Key": key, "UploadId": upload_id}
        params["PartNumber"] = check_part_number(part_number)
        if size is not None:  # Content-Length becomes a signed header: no other length is accepted
            params["ContentLength"] = int(size)
        return self._presigner.generate_presigned_url(
            "upload_part", Params=params, ExpiresIn=expires_s or self.presign_expiry_s
        )

    def upload_part(self, key: str, upload_id: str, part_number: int, data: bytes | BinaryIO) -> str:
        validate_key(key)
        n = check_part_number(part_number)
        with _errors(f"upload part {n} of {key!r}"):
            r = self.client.upload_part(
                Bucket=self.bucket, Key=key, UploadId=upload_id, PartNumber=n, Body=data
            )
        return r["ETag"].strip('"')

    def list_parts(
        self, key: str, upload_id: str, etags: Mapping[int, str] | None = None
    ) -> builtins.list[PartStat]:
        """The parts received; one per part number (SeaweedFS lists every upload of a part number that
        was sent again, real S3 only the last): the one `etags` names, else the newest (LastModified has
        one-second steps, so two sends within a second tie: name the ETag to be sure)."""
        named = {n: e.strip('"') for n, e in (etags or {}).items()}
        validate_key(key)
        pages = self.client.get_paginator("list_parts").paginate(
            Bucket=self.bucket, Key=key, UploadId=upload_id
        )
        sent: dict[int, list[PartStat]] = {}
        with _errors(f"list parts of {key!r}"):
            for page in pages:
                for p in page.get("Parts", []):
                    part = PartStat(
                        int(p["PartNumber"]), int(p["Size"]), str(p["ETag"]).strip('"'), p.get("LastModified")
                    )
                    sent.setdefault(part.part_number, []).append(part)
        return [_chosen(sent[n], named.get(n)) for n in sorted(sent)]

    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> ObjectStat:
        validate_key(key)
        if not parts:
            raise ValueError("complete_multipart needs at least one part")
        listed: builtins.list[dict[str, Any]] = [
            {"PartNumber": check_part_number(n), "ETag": f'"{e.strip(chr(34))}"'} for n, e in parts
        ]
        with _errors(f"complete multipart upload {key!r}"):
            self.client.complete_multipart_upload(
                Bucket=self.bucket,
                Key=key,
                UploadId=upload_id,
                MultipartUpload={"Parts": sorted(listed, key=lambda p: p["PartNumber"])},
            )
        return self.stat(key)

    def abort_multipart(self, key: str, upload_id: str) -> None:
        validate_key(key)
        with _errors(f"abort multipart upload {key!r}"):
            self.client.abort_multipart_upload(Bucket=self.bucket, Key=key, UploadId=upload_id)
