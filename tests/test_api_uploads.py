"""Resumable multipart uploads: presigned part URLs on S3 (SeaweedFS), parts through the API on local
storage; completion checks (size, sha256, decoding) and aborts."""

from __future__ import annotations

import hashlib
import uuid

import httpx
import pytest

from shared.storage import StorageKeyError
from shared.storage.keys import image_key_for_name

MB = 1024 * 1024


def _project(env, tenant) -> str:
    r = env.client.post("/projects", json={"name": f"p-{uuid.uuid4().hex[:8]}"}, headers=tenant.headers)
    assert r.status_code == 201
    return r.json()["id"]


def _send_part(env, tenant, pid: str, up: dict, data: bytes, n: int) -> str:
    """PUT part n where GET .../parts/{n} says (presigned storage URL, or the API); its ETag."""
    r = env.client.get(f"/projects/{pid}/uploads/{up['id']}/parts/{n}", headers=tenant.headers)
    assert r.status_code == 200, r.text
    target = r.json()
    chunk = data[(n - 1) * up["part_size"] : n * up["part_size"]]
    assert target["size"] == len(chunk) and target["method"] == "PUT"
    if target["needs_auth"]:  # the API receives the part (local storage)
        assert target["url"].startswith("http://testserver/projects/")
        put = env.client.put(target["url"], content=chunk, headers=tenant.headers)
        assert put.status_code == 200, put.text
        return put.json()["etag"]
    put = httpx.put(target["url"], content=chunk, timeout=30)  # straight to the bucket, no credentials
    assert put.status_code == 200, put.text
    return put.headers["etag"]


def _send_parts(env, tenant, pid: str, up: dict, data: bytes) -> list[dict]:
    """Every part of the upload; [{part_number, etag}]."""
    return [
        {"part_number": n, "etag": _send_part(env, tenant, pid, up, data, n)}
        for n in range(1, up["part_count"] + 1)
    ]


def test_multipart_upload_registers_the_image(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    data = make_jpeg(320, 240, seed=7, padding=6 * MB)  # two parts of 5 MiB at least
    sha = hashlib.sha256(data).hexdigest()
    r = c.post(
        f"/projects/{pid}/uploads",
        json={"name": "aerial/BIG.jpg", "size": len(data), "sha256": sha},
        headers=t.headers,
    )
    assert r.status_code == 201, r.text
    up = r.json()
    assert up["part_count"] == 2 and up["part_size"] == api_env.settings.upload_part_size
    assert up["parts_via"] == ("presigned" if api_env.s3 else "api")
    assert [u["id"] for u in c.get(f"/projects/{pid}/uploads", headers=t.headers).json()] == [up["id"]]
    # a second upload of the same name is refused while this one runs; so is a direct upload
    again = c.post(f"/projects/{pid}/uploads", json={"name": "aerial/BIG.jpg", "size": 10}, headers=t.headers)
    assert again.status_code == 409
    direct = c.post(
        f"/projects/{pid}/images",
        params={"set": "aerial"},
        files={"f": ("BIG.jpg", make_jpeg())},
        headers=t.headers,
    )
    assert direct.status_code == 409
    assert c.get(f"/projects/{pid}/uploads/{up['id']}/parts/3", headers=t.headers).status_code == 422

    parts = _send_parts(api_env, t, pid, up, data)
    r = c.post(f"/projects/{pid}/uploads/{up['id']}/complete", json={"parts": parts[:1]}, headers=t.headers)
    assert r.status_code == 422  # a part missing
    r = c.post(f"/projects/{pid}/uploads/{up['id']}/complete", json={"parts": parts[::-1]}, headers=t.headers)
    assert r.status_code == 201, r.text
    image = r.json()
    assert image["name"] == "aerial/BIG.jpg" and image["sha256"] == sha and image["created"] is True
    assert (image["width"], image["height"], image["size_bytes"]) == (320, 240, len(data))
    assert api_env.storage.get_bytes(image_key_for_name(t.id, pid, "aerial/BIG.jpg")) == data
    assert c.get(f"/projects/{pid}/images/aerial/BIG.jpg", headers=t.headers).json()["sha256"] == sha
    assert c.get(f"/projects/{pid}/uploads", headers=t.headers).json() == []
    assert c.get(f"/projects/{pid}/uploads/{up['id']}", headers=t.headers).status_code == 404
    r = c.post(f"/projects/{pid}/uploads", json={"name": "aerial/BIG.jpg", "size": 10}, headers=t.headers)
    assert r.status_code == 409 and r.json()["detail"]["sha256"] == sha  # exists now


def test_multipart_upload_failing_its_checks_is_deleted(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    good = make_jpeg(seed=3, width=320, height=240)
    n = len(good)
    garbled = good[: n // 2] + bytes(min(2000, n // 3)) + good[n // 2 + min(2000, n // 3) :]  # markers intact
    cases = {
        "aerial/SHA.jpg": (good, "0" * 64, "does not match"),
        "aerial/TRUNC.jpg": (good[:-100], None, "truncated JPEG"),
        "aerial/GARBLED.jpg": (garbled, None, "corrupt JPEG"),
        "ground/JUNK.png": (b"\x89PNG not really" * 50, None, "cannot decode"),
    }
    for name, (data, sha, needle) in cases.items():
        body = {"name": name, "size": len(data), **({"sha256": sha} if sha else {})}
        up = c.post(f"/projects/{pid}/uploads", json=body, headers=t.headers).json()
        parts = _send_parts(api_env, t, pid, up, data)
        r = c.post(f"/projects/{pid}/uploads/{up['id']}/complete", json={"parts": parts}, headers=t.headers)
        assert r.status_code == 422, (name, r.text)
        assert needle in r.json()["detail"]["errors"][0], r.json()
        assert not api_env.storage.exists(image_key_for_name(t.id, pid, name))
        assert c.get(f"/projects/{pid}/uploads/{up['id']}", headers=t.headers).status_code == 404
    assert c.get(f"/projects/{pid}/images", headers=t.headers).json() == []


def test_multipart_upload_refusals_and_abort(api_env, make_jpeg, monkeypatch) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    for body, status in [
        ({"name": "A1.jpg", "size": 10}, 422),  # no set
        ({"name": "sky/A1.jpg", "size": 10}, 422),
        ({"name": "aerial/../A1.jpg", "size": 10}, 422),
        ({"name": "aerial/A1.txt", "size": 10}, 422),
        ({"name": "aerial/A1.jpg", "size": 0}, 422),
        ({"name": "aerial/A1.jpg", "size": 10, "sha256": "xyz"}, 422),
    ]:
        assert c.post(f"/projects/{pid}/uploads", json=body, headers=t.headers).status_code == status, body
    monkeypatch.setattr(api_env.settings, "max_upload_bytes", 1000)
    r = c.post(f"/projects/{pid}/uploads", json={"name": "aerial/A1.jpg", "size": 1001}, headers=t.headers)
    assert r.status_code == 413 and "upload limit" in r.json()["detail"]
    monkeypatch.undo()

    data = make_jpeg(seed=4)
    up = c.post(
        f"/projects/{pid}/uploads", json={"name": "aerial/A1.jpg", "size": len(data)}, headers=t.headers
    )
    uid = up.json()["id"]
    part = f"/projects/{pid}/uploads/{uid}/parts/1"
    assert c.put(part, content=data[:-1], headers=t.headers).status_code == 422  # short part
    assert c.put(part, content=data + b"x", headers=t.headers).status_code == 413  # long part
    assert c.put(part, content=data, headers=t.headers).status_code == 200  # through the API on any backend
    assert c.delete(f"/projects/{pid}/uploads/{uid}", headers=t.headers).status_code == 204
    assert c.delete(f"/projects/{pid}/uploads/{uid}", headers=t.headers).status_code == 404
    assert c.put(part, content=data, headers=t.headers).status_code == 404
    assert c.get(f"/projects/{pid}/uploads/not-an-id", headers=t.headers).status_code == 404
    assert not api_env.storage.exists(image_key_for_name(t.id, pid, "aerial/A1.jpg"))
    # the name is free again once aborted
    up = c.post(
        f"/projects/{pid}/uploads", json={"name": "aerial/A1.jpg", "size": len(data)}, headers=t.headers
    )
    assert up.status_code == 201
    # deleting the project drops unfinished uploads with everything else
    assert c.delete(f"/projects/{pid}", headers=t.headers).status_code == 204
    assert api_env.storage.list(f"tenants/{t.id}/") == []


def test_resume_from_the_listed_parts(api_env, make_jpeg) -> None:
    """A client that lost its ETags asks for the parts received (number, size, ETag; from the storage's
    list of parts), sends the missing one, and completes with the listed ETags, or with none at all."""
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    data = make_jpeg(320, 240, seed=8, padding=6 * MB)
    sha = hashlib.sha256(data).hexdigest()
    for name, explicit in (("aerial/R1.jpg", True), ("aerial/R2.jpg", False)):
        body = {"name": name, "size": len(data), "sha256": sha}
        up = c.post(f"/projects/{pid}/uploads", json=body, headers=t.headers).json()
        base = f"/projects/{pid}/uploads/{up['id']}"
        listed = c.get(f"{base}/parts", headers=t.headers).json()
        assert listed == {"id": up["id"], "part_count": 2, "parts": [], "missing": [1, 2], "wrong_size": []}
        etag1 = _send_part(api_env, t, pid, up, data, 1)  # part 1 only; then the client goes away
        r = c.post(f"{base}/complete", json={}, headers=t.headers)
        assert r.status_code == 422 and "missing [2]" in r.json()["detail"], r.text
        r = c.get(f"{base}/parts", headers=t.headers)
        assert r.status_code == 200, r.text
        got = r.json()
        assert got["missing"] == [2] and got["wrong_size"] == []
        assert [(p["part_number"], p["size"], p["etag"].strip('"')) for p in got["parts"]] == [
            (1, up["part_size"], etag1.strip('"'))
        ]
        _send_parts(api_env, t, pid, up, data)  # every part again (idempotent), ETags dropped
        got = c.get(f"{base}/parts", headers=t.headers).json()
        assert got["missing"] == [] and [p["size"] for p in got["parts"]] == [
            up["part_size"],
            len(data) - up["part_size"],
        ]
        parts = [{"part_number": p["part_number"], "etag": p["etag"]} for p in got["parts"]]
        r = c.post(f"{base}/complete", json={"parts": parts} if explicit else {}, headers=t.headers)
        assert r.status_code == 201, r.text
        assert r.json()["sha256"] == sha and r.json()["name"] == name
        assert api_env.storage.get_bytes(image_key_for_name(t.id, pid, name)) == data
        assert c.get(f"{base}/parts", headers=t.headers).status_code == 404  # finished
    other = api_env.tenant()
    assert c.get(f"/projects/{pid}/uploads/{up['id']}/parts", headers=other.headers).status_code == 404


def test_concurrent_starts_of_one_name(api_env, make_jpeg, monkeypatch) -> None:
    """Two starts of the same name at once: exactly one wins (201), the other gets 409 and leaves no
    storage upload behind. On PostgreSQL both pass the "none in progress" check (the unique name
    decides); on SQLite the second waits for the first's write lock and finds its upload in progress."""
    import threading

    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    storage = api_env.storage
    both_checked = threading.Barrier(2, timeout=20 if api_env.s3 else 2)
    created, aborted = [], []
    real_create, real_abort = storage.create_multipart, storage.abort_multipart

    def create_multipart(key, content_type=None):  # the real call, once both requests got this far
        try:
            both_checked.wait()
        except threading.BrokenBarrierError:
            assert not api_env.s3  # SQLite: the other request waits for this one's write lock
        upload_id = real_create(key, content_type=content_type)
        created.append(upload_id)
        return upload_id

    def abort_multipart(key, upload_id):
        aborted.append(upload_id)
        return real_abort(key, upload_id)

    monkeypatch.setattr(storage, "create_multipart", create_multipart)
    monkeypatch.setattr(storage, "abort_multipart", abort_multipart)
    body = {"name": "aerial/RACE.jpg", "size": 12345}
    results = []

    def start() -> None:
        results.append(c.post(f"/projects/{pid}/uploads", json=body, headers=t.headers))

    threads = [threading.Thread(target=start) for _ in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(60)
    assert sorted(r.status_code for r in results) == [201, 409], [r.text for r in results]
    loser = next(r for r in results if r.status_code == 409)
    assert "already in progress" in loser.json()["detail"]
    winner = next(r for r in results if r.status_code == 201).json()
    assert [u["id"] for u in c.get(f"/projects/{pid}/uploads", headers=t.headers).json()] == [winner["id"]]
    if not api_env.s3:
        assert len(created) == 1 and aborted == []  # the loser never got as far as the storage
        return
    assert len(created) == 2 and len(aborted) == 1  # the loser's storage upload was aborted
    with pytest.raises(StorageKeyError):
        storage.list_parts(image_key_for_name(t.id, pid, "aerial/RACE.jpg"), aborted[0])


def _wait_checked(env, tenant, pid: str, timeout_s: float = 30.0) -> list[dict]:
    """The project's uploads once none is verifying."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        ups = env.client.get(f"/projects/{pid}/uploads", headers=tenant.headers).json()
        if not any(u["state"] == "verifying" for u in ups) or time.monotonic() > deadline:
            return ups
        time.sleep(0.05)


def test_completion_without_waiting_checks_in_the_background(api_env, make_jpeg) -> None:
    """wait false: 202 once assembled; the check registers the image, or leaves the upload rejected with
    the reason (its object deleted) and the project's jobs refused until it is uploaded again; a job
    cannot start while an upload is being checked; an upload left verifying (a process died) is taken
    again by the sweep."""
    from datetime import timedelta

    from conftest import jobbable_project

    from shared.db.models import Upload, utcnow

    c, t = api_env.client, api_env.tenant()
    pid = jobbable_project(c, t.headers, make_jpeg)  # 3 aerial and 1 ground image with POS
    good = make_jpeg(seed=5, width=320, height=240)
    n = len(good)
    garbled = good[: n // 2] + bytes(min(2000, n // 3)) + good[n // 2 + min(2000, n // 3) :]

    def send(name: str, data: bytes) -> dict:
        up = c.post(
            f"/projects/{pid}/uploads", json={"name": name, "size": len(data)}, headers=t.headers
        ).json()
        parts = _send_parts(api_env, t, pid, up, data)
        r = c.post(
            f"/projects/{pid}/uploads/{up['id']}/complete",
            json={"parts": parts, "wait": False},
            headers=t.headers,
        )
        assert r.status_code == 202, r.text
        assert r.json()["state"] == "verifying" and r.json()["id"] == up["id"]
        return up

    send("aerial/A9.jpg", good)
    bad = send("aerial/BAD.jpg", garbled)
    ups = _wait_checked(api_env, t, pid)
    assert [(u["name"], u["state"]) for u in ups] == [("aerial/BAD.jpg", "rejected")]
    assert "corrupt JPEG" in ups[0]["error"]
    assert not api_env.storage.exists(image_key_for_name(t.id, pid, "aerial/BAD.jpg"))
    image = c.get(f"/projects/{pid}/images/aerial/A9.jpg", headers=t.headers).json()
    assert image["sha256"] == hashlib.sha256(good).hexdigest() and (image["width"], image["height"]) == (
        320,
        240,
    )
    api_env.dispatcher.calls.clear()
    r = c.post(f"/projects/{pid}/jobs", json={}, headers=t.headers)
    assert (
        r.status_code == 409
        and "aerial/BAD.jpg" in r.json()["detail"]
        and "corrupt JPEG" in r.json()["detail"]
    )
    # uploaded again (the new start replaces the rejected upload), with the job's POS rows
    send("aerial/BAD.jpg", make_jpeg(seed=6))
    assert _wait_checked(api_env, t, pid) == []
    assert c.get(f"/projects/{pid}/uploads/{bad['id']}", headers=t.headers).status_code == 404

    # an upload being checked holds the jobs back (409 with Retry-After)
    up = c.post(
        f"/projects/{pid}/uploads", json={"name": "ground/G9.jpg", "size": 10}, headers=t.headers
    ).json()
    with api_env.session() as s:
        row = s.get(Upload, up["id"])
        row.state, row.verify_started_at = "verifying", utcnow() - timedelta(hours=1)
        s.commit()
    r = c.post(f"/projects/{pid}/jobs", json={}, headers=t.headers)
    assert (
        r.status_code == 409
        and "still being checked" in r.json()["detail"]
        and r.headers["retry-after"] == "2"
    )
    # ... until the sweep takes it again (its claim is an hour old): nothing was assembled, so rejected
    verifier = api_env.app.state.verifier
    assert verifier.sweep() == [up["id"]]
    assert [(u["name"], u["state"]) for u in _wait_checked(api_env, t, pid)] == [
        ("ground/G9.jpg", "rejected")
    ]
    assert verifier.sweep() == []  # rejected: not taken again


def test_the_start_gives_every_part_url_with_presigned_parts(api_env, make_jpeg) -> None:
    """With S3 the answer to the start holds the presigned URL of every part: the parts go to the bucket
    with no request to the API between the start and the completion. Local storage gives none (the
    parts go through the API route)."""
    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    data = make_jpeg(320, 240, seed=8, padding=11 * MB)  # three parts
    r = c.post(
        f"/projects/{pid}/uploads", json={"name": "aerial/URLS.jpg", "size": len(data)}, headers=t.headers
    )
    assert r.status_code == 201, r.text
    up = r.json()
    if not api_env.s3:
        assert up["part_urls"] is None
        return
    urls = up["part_urls"]
    assert [u["part_number"] for u in urls] == [1, 2, 3] and not any(u["needs_auth"] for u in urls)
    assert [u["size"] for u in urls] == [up["part_size"], up["part_size"], len(data) - 2 * up["part_size"]]
    parts = []
    for u in urls:
        chunk = data[(u["part_number"] - 1) * up["part_size"] : u["part_number"] * up["part_size"]]
        put = httpx.put(u["url"], content=chunk, timeout=30)
        assert put.status_code == 200, put.text
        parts.append({"part_number": u["part_number"], "etag": put.headers["etag"]})
    r = c.post(f"/projects/{pid}/uploads/{up['id']}/complete", json={"parts": parts}, headers=t.headers)
    assert r.status_code == 201, r.text
    assert api_env.storage.get_bytes(image_key_for_name(t.id, pid, "aerial/URLS.jpg")) == data
    # a later listing does not repeat them
    assert all(
        u.get("part_urls") is None for u in c.get(f"/projects/{pid}/uploads", headers=t.headers).json()
    )


def test_a_part_of_the_wrong_size_is_refused_before_anything_is_assembled(api_env, make_jpeg) -> None:
    """A presigned part URL signs the part's length: the storage refuses a PUT of any other length. A
    part of the wrong size that the storage holds anyway is refused when the upload completes (422 naming
    it), before the parts are assembled or read; the right part sent again completes the upload."""
    from datetime import timedelta

    from shared.db.models import Upload, utcnow

    c, t = api_env.client, api_env.tenant()
    pid = _project(api_env, t)
    data = make_jpeg(seed=11)
    up = c.post(
        f"/projects/{pid}/uploads", json={"name": "aerial/P.jpg", "size": len(data)}, headers=t.headers
    )
    up = up.json()
    target = c.get(f"/projects/{pid}/uploads/{up['id']}/parts/1", headers=t.headers).json()
    big = data + bytes(len(data))
    if target["needs_auth"]:  # the API receives the part: it counts the bytes
        r = c.put(target["url"], content=big, headers=t.headers)
    else:  # straight to the bucket, under the signed length
        r = httpx.put(target["url"], content=big, timeout=30)
    assert r.status_code in (403, 413), r.text
    with api_env.session() as s:
        row = s.get(Upload, up["id"])
        key, storage_id = row.storage_key, row.storage_upload_id
    etag = api_env.storage.upload_part(key, storage_id, 1, big)  # the storage holds a wrong part anyway
    r = c.post(
        f"/projects/{pid}/uploads/{up['id']}/complete",
        json={"parts": [{"part_number": 1, "etag": etag}]},
        headers=t.headers,
    )
    assert r.status_code == 422 and f"part 1 is {len(big)} bytes, not {len(data)}" in r.text
    assert not api_env.storage.exists(key)  # nothing assembled
    etag = _send_part(api_env, t, pid, up, data, 1)
    r = c.post(
        f"/projects/{pid}/uploads/{up['id']}/complete",
        json={"parts": [{"part_number": 1, "etag": etag}]},
        headers=t.headers,
    )
    assert r.status_code == 201, r.text

    # an upload left open past the expiry is aborted, its parts deleted
    up = c.post(
        f"/projects/{pid}/uploads", json={"name": "aerial/Q.jpg", "size": len(data)}, headers=t.headers
    )
    up = up.json()
    _send_part(api_env, t, pid, up, data, 1)
    with api_env.session() as s:
        row = s.get(Upload, up["id"])
        key, storage_id = row.storage_key, row.storage_upload_id
    assert [p.part_number for p in api_env.storage.list_parts(key, storage_id)] == [1]
    verifier = api_env.app.state.verifier
    assert up["id"] not in verifier.expire()
    assert up["id"] in verifier.expire(now=utcnow() + timedelta(hours=25))
    assert c.get(f"/projects/{pid}/uploads/{up['id']}", headers=t.headers).status_code == 404
    with pytest.raises(StorageKeyError):  # the multipart upload was aborted: its parts are gone
        api_env.storage.list_parts(key, storage_id)
