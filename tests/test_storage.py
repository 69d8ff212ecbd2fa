"""One contract for every storage backend: LocalStorage in a tmp folder, S3Storage on a private SeaweedFS."""

from __future__ import annotations

import hashlib
import io
import os
import urllib.request
import uuid
from pathlib import Path

import httpx
import pytest
from servers import S3Server

from shared.config import Settings
from shared.storage import (
    InvalidKeyError,
    LocalStorage,
    S3Storage,
    Storage,
    StorageKeyError,
    get_storage,
)
from shared.storage import keys as K

MB = 1024 * 1024
PART = 5 * MB  # the S3 minimum part size (all parts but the last)


@pytest.fixture(scope="module")
def s3_storage(s3_server: S3Server) -> S3Storage:
    """S3Storage on the session's SeaweedFS bucket, with 5 MB multipart parts."""
    return S3Storage(
        s3_server.bucket,
        endpoint_url=s3_server.endpoint_url,
        region=s3_server.region,
        access_key=s3_server.access_key,
        secret_key=s3_server.secret_key,
        multipart_threshold=PART,
        multipart_chunksize=PART,
    )


@pytest.fixture(params=["local", "s3"])
def storage(request: pytest.FixtureRequest, tmp_path: Path) -> Storage:
    if request.param == "local":
        return LocalStorage(tmp_path / "store")
    return request.getfixturevalue("s3_storage")


@pytest.fixture
def ns() -> str:
    """A key prefix of its own for each test (the S3 bucket is shared by the session)."""
    return f"t-{uuid.uuid4().hex[:10]}/"


def test_put_get_exists_stat_delete(storage: Storage, ns: str) -> None:
    key = ns + "a/b.txt"
    assert not storage.exists(key)
    st = storage.put_bytes(key, b"hello", content_type="text/plain")
    assert st.size == 5 and st.etag
    assert storage.exists(key)
    assert storage.get_bytes(key) == b"hello"
    assert storage.stat(key).size == 5
    storage.put_bytes(key, b"replaced")  # overwrite
    assert storage.get_bytes(key) == b"replaced"
    storage.delete(key)
    assert not storage.exists(key)
    storage.delete(key)  # deleting a missing object is fine


def test_missing_key_raises_storage_key_error(storage: Storage, ns: str, tmp_path: Path) -> None:
    key = ns + "missing.bin"
    for call in (
        lambda: storage.get_bytes(key),
        lambda: storage.stat(key),
        lambda: storage.open_read(key),
        lambda: storage.download(key, tmp_path / "out.bin"),
    ):
        with pytest.raises(StorageKeyError) as err:
            call()
        assert isinstance(err.value, KeyError)
        assert "missing.bin" in str(err.value)
    assert not (tmp_path / "out.bin").exists()


def test_list_and_delete_prefix(storage: Storage, ns: str) -> None:
    for k in ("a/1", "a/2", "a/b/3", "ab/4", "c/5"):
        storage.put_bytes(ns + k, k.encode())
    assert storage.list(ns + "a/") == [ns + "a/1", ns + "a/2", ns + "a/b/3"]
    assert storage.list(ns + "a") == [ns + "a/1", ns + "a/2", ns + "a/b/3", ns + "ab/4"]  # a string prefix
    assert storage.list(ns + "zzz/") == []
    assert storage.delete_prefix(ns + "a/") == 3
    assert storage.list(ns) == [ns + "ab/4", ns + "c/5"]
    with pytest.raises(ValueError):
        storage.delete_prefix("")
    assert storage.delete_prefix(ns) == 2
    assert storage.list(ns) == []


def test_large_file_multipart_and_download(storage: Storage, ns: str, tmp_path: Path) -> None:
    data = os.urandom(12 * MB)
    src = tmp_path / "big.bin"
    src.write_bytes(data)
    st = storage.put_file(ns + "big.bin", src)
    assert st.size == len(data)
    if isinstance(storage, S3Storage):
        assert st.etag.endswith("-3"), st.etag  # uploaded as 3 parts of <= 5 MB
    out = storage.download(ns + "big.bin", tmp_path / "dl" / "big.bin")
    assert hashlib.sha256(out.read_bytes()).digest() == hashlib.sha256(data).digest()


def test_streaming_read_and_write(storage: Storage, ns: str) -> None:
    data = os.urandom(3 * MB + 17)
    storage.put_stream(ns + "s.bin", io.BytesIO(data))
    got, chunks = bytearray(), 0
    with storage.open_read(ns + "s.bin") as f:
        while chunk := f.read(MB):
            got += chunk
            chunks += 1
    assert bytes(got) == data and chunks >= 4


def test_presigned_get_url_downloads(storage: Storage, ns: str) -> None:
    storage.put_bytes(ns + "p/x.json", b'{"ok": true}', content_type="application/json")
    url = storage.presigned_get_url(ns + "p/x.json", expires_s=60)
    assert url is not None
    with urllib.request.urlopen(url, timeout=10) as r:  # http:// (S3) or file:// (local)
        assert r.read() == b'{"ok": true}'
    if isinstance(storage, S3Storage):
        assert httpx.get(url, timeout=10).content == b'{"ok": true}'
        assert httpx.get(url.split("?")[0], timeout=10).status_code == 403  # unsigned: refused


def test_client_multipart_upload(storage: Storage, ns: str) -> None:
    """The API flow: create, the client sends parts (to presigned URLs, or through the API), complete."""
    key = ns + "upload/big.bin"
    data = os.urandom(2 * PART + 1234)
    upload_id = storage.create_multipart(key)
    parts = []
    for i, off in enumerate(range(0, len(data), PART), start=1):
        chunk = data[off : off + PART]
        url = storage.presigned_part_url(key, upload_id, i)
        if url is None:  # local backend: the API receives the part and stores it
            etag = storage.upload_part(key, upload_id, i, io.BytesIO(chunk))
        else:
            r = httpx.put(url, content=chunk, timeout=30)
            assert r.status_code == 200, r.text
            etag = r.headers["etag"]
        parts.append((i, etag))
    assert not storage.exists(key)
    st = storage.complete_multipart(key, upload_id, list(reversed(parts)))  # any order
    assert st.size == len(data)
    assert storage.get_bytes(key) == data


def test_list_parts_resumes_an_upload(storage: Storage, ns: str) -> None:
    """list_parts gives back the parts received (number, size, ETag): enough to complete without the
    ETags the client kept; an aborted upload has none to list."""
    key = ns + "resumed.bin"
    data = os.urandom(PART + 777)
    upload_id = storage.create_multipart(key)
    assert storage.list_parts(key, upload_id) == []
    sent = {}
    for n, chunk in ((2, data[PART:]), (1, data[:PART])):  # any order
        url = storage.presigned_part_url(key, upload_id, n)
        if url is None:
            sent[n] = storage.upload_part(key, upload_id, n, chunk)
        else:
            r = httpx.put(url, content=chunk, timeout=30)
            assert r.status_code == 200, r.text
            sent[n] = r.headers["etag"].strip('"')
    listed = storage.list_parts(key, upload_id)
    assert [(p.part_number, p.size, p.etag) for p in listed] == [(1, PART, sent[1]), (2, 777, sent[2])]
    st = storage.complete_multipart(key, upload_id, [(p.part_number, p.etag) for p in listed])
    assert st.size == len(data) and storage.get_bytes(key) == data
    other = storage.create_multipart(ns + "gone.bin")
    storage.abort_multipart(ns + "gone.bin", other)
    with pytest.raises(StorageKeyError):
        storage.list_parts(ns + "gone.bin", other)


def test_a_part_sent_twice_is_listed_as_the_send_named_by_its_etag(storage: Storage, ns: str) -> None:
    """A part sent again within the same second (S3's LastModified has one-second steps, so "the newest"
    is a guess): list_parts gives the send whose ETag the caller names (the one it will complete with)."""
    key = ns + "twice.bin"
    upload_id = storage.create_multipart(key)
    first = storage.upload_part(key, upload_id, 1, b"a" * 3000)
    second = storage.upload_part(key, upload_id, 1, b"b" * 1500)
    assert [p.part_number for p in storage.list_parts(key, upload_id)] == [1]  # one per part number
    named = storage.list_parts(key, upload_id, {1: second})
    assert [(p.size, p.etag) for p in named] == [(1500, second)]
    # a store that keeps both sends (SeaweedFS) gives the one named; one that keeps the last, the last
    assert storage.list_parts(key, upload_id, {1: first})[0].etag in (first, second)
    storage.abort_multipart(key, upload_id)


def test_abort_multipart(storage: Storage, ns: str) -> None:
    key = ns + "aborted.bin"
    upload_id = storage.create_multipart(key)
    etag = storage.upload_part(key, upload_id, 1, b"x" * 1000)
    storage.abort_multipart(key, upload_id)
    with pytest.raises(StorageKeyError):
        storage.complete_multipart(key, upload_id, [(1, etag)])
    assert not storage.exists(key)


@pytest.mark.parametrize(
    "bad", ["../x", "/etc/passwd", "a/../../b", "a\\b", "a//b", "a/./b", "", "a/", "a\x00b"]
)
def test_unsafe_keys_are_rejected(storage: Storage, bad: str) -> None:
    with pytest.raises(InvalidKeyError):
        storage.put_bytes(bad, b"x")
    with pytest.raises(InvalidKeyError):
        storage.get_bytes(bad)


def test_local_writes_stay_inside_root(tmp_path: Path) -> None:
    store = LocalStorage(tmp_path / "root")
    store.put_bytes("x/y.bin", b"1")
    assert (tmp_path / "root" / "x" / "y.bin").read_bytes() == b"1"
    assert store.list("") == ["x/y.bin"]  # internal temp/upload folders are hidden
    assert not list((tmp_path / "root" / ".tmp").iterdir())  # no temp file left behind
    with pytest.raises(InvalidKeyError):
        store.put_bytes(".uploads/z", b"1")
    store.delete("x/y.bin")
    assert not (tmp_path / "root" / "x").exists()  # empty folders pruned


def test_key_layout() -> None:
    assert K.image_key("t1", "p1", "aerial", "A0001.jpg") == "tenants/t1/projects/p1/images/aerial/A0001.jpg"
    assert K.image_key_for_name("t1", "p1", "ground/G1.jpg") == "tenants/t1/projects/p1/images/ground/G1.jpg"
    assert K.job_key("t1", "p1", "j1", "match", "out/m.h5") == "tenants/t1/projects/p1/jobs/j1/match/out/m.h5"
    assert K.job_prefix("t1", "p1", "j1") == "tenants/t1/projects/p1/jobs/j1/"
    for call in (
        lambda: K.image_key("t1", "..", "aerial", "a.jpg"),
        lambda: K.image_key("t1", "p1", "aerial", "../a.jpg"),
        lambda: K.image_key_for_name("t1", "p1", "A0001.jpg"),
        lambda: K.job_key("t1", "p1", "j1", "match", "../../../x"),
        lambda: K.job_key("t1", "p1", "j1", "match", "/abs"),
        lambda: K.tenant_prefix("a/b"),
    ):
        with pytest.raises(InvalidKeyError):
            call()


def test_get_storage_factory(tmp_path: Path) -> None:
    local = get_storage(Settings(data_dir=tmp_path, storage="local"))
    assert isinstance(local, LocalStorage) and local.root == (tmp_path / "storage").resolve()
    s3 = get_storage(Settings(storage="s3", s3_endpoint_url="http://127.0.0.1:1", s3_bucket="b-x"))
    assert isinstance(s3, S3Storage) and s3.bucket == "b-x"
