"""The REST API on SQLite + local storage and on PostgreSQL + S3 (SeaweedFS): auth, tenants, projects,
images, POS, job options and job control. The dispatcher is a recorder (see conftest.RecordingDispatcher)."""

from __future__ import annotations

import hashlib
import logging
import time
import uuid
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.bootstrap import create_tenant_with_key
from api.config import ApiSettings
from api.main import create_app
from shared.db import crud
from shared.db.models import JobStatus
from shared.db.session import upgrade_database
from shared.storage.keys import image_key_for_name, project_prefix

POS_HEADER = "# midview-pos v1\nname,lat,lon,h,yaw,pitch,roll,std_xy,std_z,std_att\n"


def pos_csv(names: list[str], lat: float = 55.7) -> str:
    rows = [f"{n},{lat + i * 1e-4:.7f},13.19,{100 + i:.2f},90,-45,0,0.5,1.0,1.5" for i, n in enumerate(names)]
    return POS_HEADER + "\n".join(rows) + "\n"


def new_project(env, tenant, name: str | None = None, crs: str | None = None) -> str:
    body = {"name": name or f"p-{uuid.uuid4().hex[:8]}", **({"crs": crs} if crs else {})}
    r = env.client.post("/projects", json=body, headers=tenant.headers)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def upload(env, tenant, project_id: str, files: dict[str, bytes], image_set: str = "aerial"):
    parts = [("files", (name, data, "image/jpeg")) for name, data in files.items()]
    return env.client.post(
        f"/projects/{project_id}/images", params={"set": image_set}, files=parts, headers=tenant.headers
    )


def snapshot(env, tenant, project_id: str) -> dict[str, tuple[str, bytes]]:
    """name -> (sha256, stored bytes) of every image of the project, read behind the API."""
    r = env.client.get(f"/projects/{project_id}/images", headers=tenant.headers)
    assert r.status_code == 200
    out = {}
    for im in r.json():
        key = image_key_for_name(tenant.id, project_id, im["name"])
        out[im["name"]] = (im["sha256"], env.storage.get_bytes(key))
    return out


# health, docs, auth
def test_health_readiness_and_docs(api_env) -> None:
    c = api_env.client
    assert c.get("/healthz").json() == {"status": "ok"}
    r = c.get("/readyz")
    assert r.status_code == 200 and r.json()["checks"] == {"database": "ok", "storage": "ok"}
    spec = c.get("/openapi.json").json()
    assert "/projects/{project_id}/images" in spec["paths"] and "/jobs/{job_id}/events" in spec["paths"]
    assert c.get("/docs").status_code == 200
    assert "x-request-id" in r.headers


def test_readyz_is_503_when_the_database_is_unreachable(tmp_path: Path) -> None:
    settings = ApiSettings(
        data_dir=tmp_path, database_url="postgresql+psycopg2://nobody@127.0.0.1:1/none", storage="local"
    )
    with TestClient(create_app(settings)) as c:
        r = c.get("/readyz")
    assert r.status_code == 503
    checks = r.json()["detail"]["checks"]
    assert checks["storage"] == "ok" and checks["database"] != "ok"


def test_readyz_is_503_when_the_storage_is_unreachable(tmp_path: Path) -> None:
    settings = ApiSettings(
        data_dir=tmp_path,
        storage="s3",
        s3_endpoint_url="http://127.0.0.1:1",
        s3_access_key="x",
        s3_secret_key="y",
        readyz_timeout_s=1.0,
    )
    upgrade_database(settings.database_url)
    t0 = time.monotonic()
    with TestClient(create_app(settings)) as c:
        r = c.get("/readyz")
    assert r.status_code == 503 and time.monotonic() - t0 < 10
    checks = r.json()["detail"]["checks"]
    assert checks["database"] == "ok" and checks["storage"] != "ok"


def test_readyz_checks_the_broker_with_the_celery_dispatcher(tmp_path: Path, redis_url: str) -> None:
    """dispatcher=celery adds a broker check: ok against the test Redis, 503 when nothing listens."""
    common = dict(data_dir=tmp_path, storage="local", dispatcher="celery", readyz_timeout_s=2.0)
    settings = ApiSettings(broker_url=redis_url, **common)
    upgrade_database(settings.database_url)
    with TestClient(create_app(settings)) as c:
        r = c.get("/readyz")
    assert r.status_code == 200, r.text
    assert r.json()["checks"] == {"database": "ok", "storage": "ok", "broker": "ok"}
    dead = ApiSettings(broker_url="redis://127.0.0.1:1/0", **common)
    t0 = time.monotonic()
    with TestClient(create_app(dead)) as c:
        r = c.get("/readyz")
    assert r.status_code == 503 and time.monotonic() - t0 < 10
    checks = r.json()["detail"]["checks"]
    assert checks["database"] == checks["storage"] == "ok"
    assert checks["broker"] == "failed", checks
    assert "127.0.0.1" not in r.text and "6379" not in r.text and ":1" not in r.text  # no internal address


def test_requests_are_logged(api_env, caplog: pytest.LogCaptureFixture) -> None:
    t = api_env.tenant()
    with caplog.at_level(logging.INFO, logger="midview.api.access"):
        r = api_env.client.get("/projects", headers={**t.headers, "X-Request-ID": "req-123"})
    assert r.headers["x-request-id"] == "req-123"
    lines = [rec.getMessage() for rec in caplog.records if rec.name == "midview.api.access"]
    assert any(m.startswith("GET /projects 200") and f"tenant={t.id}" in m and "req-123" in m for m in lines)


def test_auth_missing_malformed_wrong_and_revoked_keys(api_env) -> None:
    c = api_env.client
    tenant = api_env.tenant()
    assert c.get("/projects", headers=tenant.headers).status_code == 200
    cases = {
        "missing": ({}, "missing Authorization"),
        "basic": ({"Authorization": "Basic dXNlcjpwYXNz"}, "malformed"),
        "empty": ({"Authorization": "Bearer "}, "malformed"),
        "wrong": ({"Authorization": "Bearer mv_not-a-real-key-at-all"}, "invalid API key"),
        "no prefix": ({"Authorization": "Bearer something"}, "invalid API key"),
    }
    for what, (headers, reason) in cases.items():
        r = c.get("/projects", headers=headers)
        assert r.status_code == 401, what
        assert reason in r.json()["detail"], (what, r.json())
        assert r.headers["www-authenticate"].startswith("Bearer"), what
    with api_env.session() as s:  # revoked behind this process's back (midview admin key-revoke)
        key = crud.get_api_key(s, tenant.key, pepper=api_env.settings.api_key_pepper)
        crud.revoke_api_key(s, key.id)
        s.commit()
    cache = api_env.app.state.key_cache  # api.auth.KeyCache: keys that authenticated, for auth_cache_s
    ttl = api_env.settings.auth_cache_s
    assert ttl > 0 and c.get("/projects", headers=tenant.headers).status_code == 200  # still cached
    clock = cache.clock
    cache.clock = lambda: clock() + ttl + 0.01  # auth_cache_s later
    try:
        r = c.get("/projects", headers=tenant.headers)
    finally:
        cache.clock = clock
    assert r.status_code == 401 and r.json()["detail"] == "API key revoked"
    assert 'error="invalid_token"' in r.headers["www-authenticate"]


def test_bootstrap_key_and_tenant_creation(tmp_path: Path, request: pytest.FixtureRequest) -> None:
    from conftest import make_api_settings

    key = "mv_bootstrap-" + uuid.uuid4().hex
    settings = make_api_settings("sqlite-local", tmp_path, request, bootstrap_api_key=key)
    for _ in range(2):  # the second start finds the key and changes nothing
        with TestClient(create_app(settings)) as c:
            r = c.post("/projects", json={"name": f"p{_}"}, headers={"Authorization": f"Bearer {key}"})
            assert r.status_code == 201, r.text
            app = c.app
    with app.state.sessionmaker() as s:
        plaintext = create_tenant_with_key(s, "second")
        s.commit()
        assert crud.get_tenant_by_api_key(s, key, pepper="").name == "default"
        assert len(crud.list_api_keys(s, crud.get_tenant_by_api_key(s, key, pepper="").id)) == 1
    with TestClient(create_app(settings)) as c:
        r = c.get("/projects", headers={"Authorization": f"Bearer {plaintext}"})
        assert r.status_code == 200 and r.json() == []
    with pytest.raises(ValueError):
        ApiSettings(bootstrap_api_key="short")


# projects
def test_project_crud_and_duplicate_name(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    r = c.post(
        "/projects", json={"name": "survey", "description": "d", "crs": "EPSG:32633"}, headers=t.headers
    )
    assert r.status_code == 201
    pid = r.json()["id"]
    assert r.json()["name"] == "survey" and r.json()["crs"] == "EPSG:32633"
    dup = c.post("/projects", json={"name": "survey"}, headers=t.headers)
    assert dup.status_code == 409 and "already exists" in dup.json()["detail"]
    assert c.post("/projects", json={"name": ""}, headers=t.headers).status_code == 422
    assert c.post("/projects", json={"name": "x", "bogus": 1}, headers=t.headers).status_code == 422
    other = api_env.tenant()
    assert (
        c.post("/projects", json={"name": "survey"}, headers=other.headers).status_code == 201
    )  # per tenant
    assert [p["name"] for p in c.get("/projects", headers=t.headers).json()] == ["survey"]
    assert upload(api_env, t, pid, {"A1.jpg": make_jpeg()}).status_code == 201
    detail = c.get(f"/projects/{pid}", headers=t.headers).json()
    assert (
        detail["images"] == {"aerial": 1, "ground": 0} and detail["pos_records"] == 0 and detail["jobs"] == 0
    )
    prefix = project_prefix(t.id, pid)
    assert api_env.storage.list(prefix)
    assert c.delete(f"/projects/{pid}", headers=t.headers).status_code == 204
    assert c.get(f"/projects/{pid}", headers=t.headers).status_code == 404
    assert c.delete(f"/projects/{pid}", headers=t.headers).status_code == 404
    assert api_env.storage.list(prefix) == []
    assert c.get("/projects", headers=t.headers).json() == []


def test_other_tenants_ids_are_404_everywhere(api_env, make_jpeg) -> None:
    c, a, b = api_env.client, api_env.tenant(), api_env.tenant()
    pid = _ready_project(api_env, a, make_jpeg)
    job = c.post(f"/projects/{pid}/jobs", json={}, headers=a.headers).json()
    up = c.post(
        f"/projects/{pid}/uploads", json={"name": "aerial/BIG.jpg", "size": 10}, headers=a.headers
    ).json()
    with api_env.session() as s:
        art = crud.record_artifact(s, job["id"], "report", "report.json", "x/report.json")
        s.commit()
    hook = c.post("/webhooks", json={"url": "http://127.0.0.1:9/hook"}, headers=a.headers).json()
    jid, uid = job["id"], up["id"]
    requests = [
        ("GET", f"/projects/{pid}"),
        ("DELETE", f"/projects/{pid}"),
        ("GET", f"/projects/{pid}/images"),
        ("GET", f"/projects/{pid}/images/aerial/A1.jpg"),
        ("GET", f"/projects/{pid}/images/aerial/A1.jpg/download"),
        ("DELETE", f"/projects/{pid}/images/aerial/A1.jpg"),
        ("GET", f"/projects/{pid}/pos"),
        ("GET", f"/projects/{pid}/jobs"),
        ("POST", f"/projects/{pid}/jobs"),
        ("GET", f"/projects/{pid}/uploads"),
        ("GET", f"/projects/{pid}/uploads/{uid}"),
        ("GET", f"/projects/{pid}/uploads/{uid}/parts/1"),
        ("PUT", f"/projects/{pid}/uploads/{uid}/parts/1"),
        ("POST", f"/projects/{pid}/uploads/{uid}/complete"),
        ("DELETE", f"/projects/{pid}/uploads/{uid}"),
        ("POST", f"/projects/{pid}/uploads"),
        ("GET", f"/jobs/{jid}"),
        ("GET", f"/jobs/{jid}/events"),
        ("POST", f"/jobs/{jid}/cancel"),
        ("POST", f"/jobs/{jid}/rerun"),
        ("GET", f"/jobs/{jid}/artifacts"),
        ("GET", f"/jobs/{jid}/pairs"),
        ("GET", f"/jobs/{jid}/pairs/aerial/A1.jpg/ground/G1.jpg"),
        ("GET", f"/artifacts/{art.id}"),
        ("GET", f"/artifacts/{art.id}/download"),
        ("GET", f"/webhooks/{hook['id']}"),
        ("GET", f"/webhooks/{hook['id']}/deliveries"),
        ("DELETE", f"/webhooks/{hook['id']}"),
    ]
    bodies = {
        f"/projects/{pid}/jobs": {"json": {}},
        f"/projects/{pid}/uploads": {"json": {"name": "aerial/X.jpg", "size": 5}},
        f"/projects/{pid}/uploads/{uid}/complete": {"json": {"parts": [{"part_number": 1, "etag": "x"}]}},
        f"/projects/{pid}/uploads/{uid}/parts/1": {"content": b"0123456789"},
    }
    for method, url in requests:
        r = c.request(method, url, headers=b.headers, **bodies.get(url, {}))
        assert r.status_code == 404, (method, url, r.status_code, r.text)
    # uploads into another tenant's project
    assert upload(api_env, b, pid, {"A2.jpg": make_jpeg()}).status_code == 404
    r = c.post(
        f"/projects/{pid}/pos", files={"file": ("pos.csv", pos_csv(["aerial/A1.jpg"]))}, headers=b.headers
    )
    assert r.status_code == 404
    # nothing of a's changed
    assert c.get(f"/jobs/{jid}", headers=a.headers).json()["status"] == "queued"
    assert len(c.get(f"/projects/{pid}/images", headers=a.headers).json()) == 4
    assert c.get(f"/webhooks/{hook['id']}", headers=a.headers).status_code == 200
    assert c.get(f"/projects/{pid}/uploads/{uid}", headers=a.headers).status_code == 200
    assert c.get("/webhooks", headers=b.headers).json() == []


# images
def test_image_upload_stores_the_bytes(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = new_project(api_env, t)
    files = {"A0001.jpg": make_jpeg(80, 60, seed=1), "A0002.jpg": make_jpeg(96, 64, seed=2)}
    r = upload(api_env, t, pid, files)
    assert r.status_code == 201, r.text
    got = {im["name"]: im for im in r.json()["images"]}
    assert set(got) == {"aerial/A0001.jpg", "aerial/A0002.jpg"}
    for fname, data in files.items():
        im = got[f"aerial/{fname}"]
        assert im["created"] is True and im["image_set"] == "aerial"
        assert im["sha256"] == hashlib.sha256(data).hexdigest() and im["size_bytes"] == len(data)
        key = image_key_for_name(t.id, pid, im["name"])
        assert api_env.storage.get_bytes(key) == data  # the object, read back from S3 / the folder
    assert (got["aerial/A0001.jpg"]["width"], got["aerial/A0001.jpg"]["height"]) == (80, 60)
    if api_env.s3:  # straight from the bucket, not through our storage class
        obj = api_env.storage.client.get_object(
            Bucket=api_env.settings.s3_bucket, Key=image_key_for_name(t.id, pid, "aerial/A0002.jpg")
        )
        assert obj["Body"].read() == files["A0002.jpg"] and obj["ContentType"] == "image/jpeg"
    assert upload(api_env, t, pid, {"G1.png": _png()}, "ground").status_code == 201

    def names(query: dict[str, str]) -> list[str]:
        return [i["name"] for i in c.get(f"/projects/{pid}/images", params=query, headers=t.headers).json()]

    assert names({}) == ["aerial/A0001.jpg", "aerial/A0002.jpg", "ground/G1.png"]
    assert names({"set": "ground"}) == ["ground/G1.png"]
    assert c.get(f"/projects/{pid}/images", params={"set": "sky"}, headers=t.headers).status_code == 422
    one = c.get(f"/projects/{pid}/images/aerial/A0001.jpg", headers=t.headers)
    assert one.status_code == 200 and one.json()["sha256"] == got["aerial/A0001.jpg"]["sha256"]
    dl = c.get(f"/projects/{pid}/images/aerial/A0001.jpg/download", headers=t.headers)
    assert dl.content == files["A0001.jpg"] and dl.headers["content-type"] == "image/jpeg"
    assert c.get(f"/projects/{pid}/images/aerial/nope.jpg", headers=t.headers).status_code == 404
    # sanitised names: folders dropped
    r = upload(api_env, t, pid, {"../../etc/C:\\dir\\A0003.JPG": make_jpeg(seed=3)})
    assert r.status_code == 201 and r.json()["images"][0]["name"] == "aerial/A0003.JPG"
    # delete one
    assert c.delete(f"/projects/{pid}/images/aerial/A0003.JPG", headers=t.headers).status_code == 204
    assert not api_env.storage.exists(image_key_for_name(t.id, pid, "aerial/A0003.JPG"))
    assert c.delete(f"/projects/{pid}/images/aerial/A0003.JPG", headers=t.headers).status_code == 404


def _png() -> bytes:
    import cv2
    import numpy as np

    ok, buf = cv2.imencode(".png", np.full((20, 30), 128, np.uint8))
    return buf.tobytes()


def test_bad_uploads_store_nothing(api_env, make_jpeg, monkeypatch: pytest.MonkeyPatch) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = new_project(api_env, t)
    good = {"A1.jpg": make_jpeg(seed=1), "A2.jpg": make_jpeg(seed=2)}
    assert upload(api_env, t, pid, good).status_code == 201
    before = snapshot(api_env, t, pid)
    jpeg = make_jpeg(seed=5)

    def refused(files: dict[str, bytes], status: int, *needles: str) -> None:
        r = upload(api_env, t, pid, files)
        assert r.status_code == status, r.text
        text = str(r.json()["detail"])
        for needle in needles:
            assert needle in text, (needle, text)
        assert "nothing was stored" in text
        assert snapshot(api_env, t, pid) == before  # previous images all there, unchanged
        assert not api_env.storage.exists(image_key_for_name(t.id, pid, "aerial/NEW.jpg"))

    refused({"NEW.jpg": b"\x00garbage" * 100}, 422, "NEW.jpg", "not a JPEG")
    refused({"NEW.jpg": b"\xff\xd8" + b"\x00" * 200 + b"\xff\xd9"}, 422, "NEW.jpg", "cannot decode")
    refused({"NEW.jpg": jpeg[: len(jpeg) // 2]}, 422, "NEW.jpg", "truncated JPEG")
    refused({"NEW.jpg": jpeg, "BAD.jpg": jpeg[:-10]}, 422, "BAD.jpg")  # all or nothing
    refused({"NEW.jpg": jpeg, "notes.txt": b"hello"}, 422, "notes.txt", "not an image file")
    refused({"NEW.jpg": jpeg, ".hidden.jpg": jpeg}, 422, ".hidden.jpg")
    refused({"NEW.jpg": jpeg, "A1.jpg": make_jpeg(seed=9)}, 409, "A1.jpg")  # other bytes, same name
    monkeypatch.setattr(api_env.settings, "max_upload_bytes", len(jpeg) - 1)
    refused({"NEW.jpg": jpeg}, 413, "NEW.jpg", "exceeds the upload limit")
    monkeypatch.undo()
    r = c.post(f"/projects/{pid}/images", params={"set": "aerial"}, headers=t.headers, data={"x": "1"})
    assert r.status_code in (415, 422)
    r = c.post(f"/projects/{pid}/images", params={"set": "aerial"}, headers=t.headers, files={})
    assert r.status_code in (415, 422)
    assert (
        c.post(
            f"/projects/{pid}/images", params={"set": "sky"}, files={"f": ("x.jpg", jpeg)}, headers=t.headers
        ).status_code
        == 422
    )
    # same bytes again: idempotent, 200 with the existing record
    r = upload(api_env, t, pid, {"A1.jpg": good["A1.jpg"]})
    assert r.status_code == 200 and r.json()["images"][0]["created"] is False
    assert r.json()["images"][0]["sha256"] == before["aerial/A1.jpg"][0]
    # a mix of new and identical: 201, only the new one created
    r = upload(api_env, t, pid, {"A1.jpg": good["A1.jpg"], "NEW.jpg": jpeg})
    assert r.status_code == 201
    assert {i["name"]: i["created"] for i in r.json()["images"]} == {
        "aerial/A1.jpg": False,
        "aerial/NEW.jpg": True,
    }
    assert snapshot(api_env, t, pid)["aerial/A1.jpg"] == before["aerial/A1.jpg"]


def test_upload_checks_the_declared_sha256(api_env, make_jpeg) -> None:
    """`sha256` form fields (FILENAME:HEX, or a bare HEX for one file) are checked against the bytes
    received; any mismatch or malformed field rejects the whole request with a reason, storing nothing."""
    c, t = api_env.client, api_env.tenant()
    pid = new_project(api_env, t)
    a, b = make_jpeg(seed=11), make_jpeg(seed=12)
    sha_a, sha_b = hashlib.sha256(a).hexdigest(), hashlib.sha256(b).hexdigest()

    def post(files: dict[str, bytes], sha256: list[str]):
        parts = [("files", (name, data, "image/jpeg")) for name, data in files.items()]
        return c.post(
            f"/projects/{pid}/images",
            params={"set": "aerial"},
            files=parts,
            data={"sha256": sha256},
            headers=t.headers,
        )

    def refused(files: dict[str, bytes], sha256: list[str], *needles: str) -> None:
        before = snapshot(api_env, t, pid)
        r = post(files, sha256)
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        assert "nothing was stored" in detail["message"]
        text = " ".join(detail["errors"])
        for needle in needles:
            assert needle in text, (needle, text)
        assert snapshot(api_env, t, pid) == before
        for name in files:
            assert not api_env.storage.exists(image_key_for_name(t.id, pid, f"aerial/{name}"))

    # one wrong digest in the batch: the good file is not stored either
    refused({"A.jpg": a, "B.jpg": b}, [f"A.jpg:{sha_a}", f"B.jpg:{sha_a}"], "B.jpg", "does not match", sha_a)
    refused({"A.jpg": a}, [sha_b], "A.jpg", "does not match")  # a bare digest: the one file's
    refused({"A.jpg": a, "B.jpg": b}, [sha_a], "expected FILENAME:HEX")  # bare digest, two files
    refused({"A.jpg": a}, ["A.jpg:xyz"], "not a hex SHA-256")
    refused({"A.jpg": a}, [f"Z.jpg:{sha_a}"], "'Z.jpg' is no file of this request")
    refused({"A.jpg": a}, [f"A.jpg:{sha_a}", f"A.jpg:{sha_a}"], "two digests")

    # matching digests (upper case, a path as sent, a bare one for a single file): stored
    r = post({"A.jpg": a, "B.jpg": b}, [f"A.jpg:{sha_a.upper()}", f"C:\\photos\\B.jpg:{sha_b}"])
    assert r.status_code == 201, r.text
    assert {i["name"]: i["sha256"] for i in r.json()["images"]} == {
        "aerial/A.jpg": sha_a,
        "aerial/B.jpg": sha_b,
    }
    d = make_jpeg(seed=13)
    r = post({"D.jpg": d}, [hashlib.sha256(d).hexdigest()])
    assert r.status_code == 201, r.text
    assert api_env.storage.get_bytes(image_key_for_name(t.id, pid, "aerial/D.jpg")) == d
    spec = c.get("/openapi.json").json()["paths"]["/projects/{project_id}/images"]["post"]
    assert "sha256" in spec["description"]
    assert "sha256" in spec["requestBody"]["content"]["multipart/form-data"]["schema"]["properties"]


# POS
def test_pos_upload_validation_and_listing(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = new_project(api_env, t)
    assert upload(api_env, t, pid, {"A1.jpg": make_jpeg(), "A2.jpg": make_jpeg(seed=1)}).status_code == 201
    assert upload(api_env, t, pid, {"G1.jpg": make_jpeg(seed=2)}, "ground").status_code == 201

    def post(text: str, name: str = "pos.csv", **params):
        return c.post(f"/projects/{pid}/pos", files={"file": (name, text)}, params=params, headers=t.headers)

    r = post(pos_csv(["aerial/A1.jpg", "aerial/A2.jpg"]))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["format"] == "csv" and body["stored"] == 2 and body["total"] == 2
    assert body["warnings"] == ["image 'ground/G1.jpg' has no POS row"]
    rows = c.get(f"/projects/{pid}/pos", headers=t.headers).json()
    assert [row["image_name"] for row in rows] == ["aerial/A1.jpg", "aerial/A2.jpg"]
    assert rows[0]["lat"] == pytest.approx(55.7) and len(rows[0]["attitude"]) == 3
    assert rows[0]["source_format"] == "csv"

    # bad rows: 422 with one error per row, stored POS untouched
    bad = POS_HEADER + "aerial/A1.jpg,200,13.19,100,0,0,0,,,\naerial/A2.jpg,55.7,abc,100,0,0,0,,,\n"
    r = post(bad)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert detail["message"] and len(detail["errors"]) == 2
    assert "line" in detail["errors"][0] and "lat" in detail["errors"][0] and "lon" in detail["errors"][1]
    assert c.get(f"/projects/{pid}/pos", headers=t.headers).json() == rows

    # rows naming no uploaded image: 422 listing them, nothing stored
    r = post(pos_csv(["aerial/A1.jpg", "aerial/ZZZ.jpg", "ground/NOPE.jpg"], lat=10.0))
    assert r.status_code == 422
    errs = r.json()["detail"]["errors"]
    assert len(errs) == 2 and "aerial/ZZZ.jpg" in errs[0] and "ground/NOPE.jpg" in errs[1]
    assert c.get(f"/projects/{pid}/pos", headers=t.headers).json() == rows

    # other formats: JSON, geo.txt with bare names matched to the images
    r = post('[{"name": "ground/G1.jpg", "lat": 55.71, "lon": 13.2, "h": 20}]', name="pos.json")
    assert r.status_code == 200 and r.json()["format"] == "json" and r.json()["warnings"] == []
    assert r.json()["total"] == 3
    geo = "EPSG:4326\nA2.jpg 13.25 55.75 150\n"
    r = post(geo, name="geo.txt", format="auto")
    assert r.status_code == 200 and r.json()["format"] == "geotxt"
    a2 = {row["image_name"]: row for row in c.get(f"/projects/{pid}/pos", headers=t.headers).json()}
    assert a2["aerial/A2.jpg"]["lat"] == pytest.approx(55.75) and a2["aerial/A2.jpg"]["attitude"] is None
    # replace=true drops the rows the file does not name
    r = post(pos_csv(["aerial/A1.jpg"]), replace="true")
    assert r.status_code == 200 and r.json()["removed"] == 2 and r.json()["total"] == 1
    assert post("\xff\xfe garbage", name="x.csv").status_code == 422
    assert post("name,lat\n", format="xml").status_code == 422


# jobs
def _ready_project(
    env,
    tenant,
    make_jpeg,
    ground: bool = True,
    pos: bool = True,
    aerial: int = 3,
    cameras: bool = True,
    crs: str | None = None,
) -> str:
    """A project with `aerial` aerial images (one ground image), POS rows for all and a cameras.json."""
    pid = new_project(env, tenant, crs=crs)
    files = {f"A{i + 1}.jpg": make_jpeg(seed=i) for i in range(aerial)}
    assert upload(env, tenant, pid, files).status_code == 201
    names = [f"aerial/{f}" for f in files]
    if ground:
        assert upload(env, tenant, pid, {"G1.jpg": make_jpeg(seed=20)}, "ground").status_code == 201
        names.append("ground/G1.jpg")
    if pos:
        r = env.client.post(
            f"/projects/{pid}/pos", files={"file": ("pos.csv", pos_csv(names))}, headers=tenant.headers
        )
        assert r.status_code == 200
    if cameras:
        cam = {"model": "PINHOLE", "width": 64, "height": 48, "params": [60.0, 60.0, 32.0, 24.0]}
        r = env.client.put(
            f"/projects/{pid}/cameras", json={"aerial": cam, "ground": cam}, headers=tenant.headers
        )
        assert r.status_code == 200, r.text
    return pid


def test_job_options_listing(api_env) -> None:
    r = api_env.client.get("/options")
    assert r.status_code == 200
    opts = {o["name"]: o for o in r.json()["options"]}
    assert opts["stages"]["default"][0] == "aerial_sfm" and opts["stages"]["default"][-1] == "combined_sfm"
    assert opts["views_per_ground_image"] == {
        **opts["views_per_ground_image"],
        "type": "integer",
        "minimum": 1,
        "maximum": 16,
    }
    assert set(opts["matcher"]["choices"]) == {"aliked-lightglue", "sift"}
    assert set(opts["view_planner"]["choices"]) == {"paper", "ground-aware", "both"}
    assert all(o["help"] for o in opts.values())
    assert r.json()["json_schema"]["additionalProperties"] is False
    # the profiles: each option's default per profile; the one this service's workers run is offered
    profiles = {p["name"]: p for p in r.json()["profiles"]}
    assert set(profiles) == {"cpu", "gpu"} and profiles["cpu"]["offered"] and not profiles["gpu"]["offered"]
    assert opts["splat_steps"]["defaults"] == {"cpu": 3000, "gpu": 7000}
    assert opts["splat_steps"]["default"] == profiles["cpu"]["options"]["splat_steps"] == 3000
    assert opts["seed"]["defaults"] == {"cpu": 0, "gpu": 0}


def test_options_estimate_each_profiles_time_for_a_survey(api_env) -> None:
    """GET /options?aerial=&ground=: the cost model's seconds per stage of each profile's default job
    (services.pipeline.costs, fitted on bench/pipeline_time.py's runs on 2 cores) with its error; the gpu
    profile was never timed: no figure rather than a made-up one."""
    from services.pipeline import JobOptions, costs

    small = api_env.client.get("/options?aerial=20&ground=10").json()["profiles"]
    large = api_env.client.get("/options?aerial=200&ground=100").json()["profiles"]
    cpu_small, cpu_large = (next(p["estimate"] for p in ps if p["name"] == "cpu") for ps in (small, large))
    assert cpu_small["stages_s"] == costs.estimate(JobOptions(), 20, 10)["stages_s"]
    assert cpu_small["total_s"] > 0 and cpu_large["total_s"] > cpu_small["total_s"]
    assert cpu_small["relative_error"]["median"] is not None
    assert next(p["estimate"] for p in small if p["name"] == "gpu")["total_s"] is None
    assert all(p["estimate"] is None for p in api_env.client.get("/options").json()["profiles"])
    assert api_env.client.get("/options?aerial=-1&ground=3").status_code == 422


def test_a_job_takes_its_profile_from_the_workers_unless_it_names_one(api_env, make_jpeg) -> None:
    """No profile named: the one the workers offer (cpu on the embedded worker, gpu where a gsplat worker
    serves the gpu queue); named: that one; an option given explicitly wins over either profile."""
    c, t, disp = api_env.client, api_env.tenant(), api_env.dispatcher
    pid = _ready_project(api_env, t, make_jpeg)

    def create(options: dict) -> dict:
        r = c.post(f"/projects/{pid}/jobs", json={"options": options}, headers=t.headers)
        assert r.status_code == 201, r.text
        return r.json()["options"]

    try:
        cpu = create({})
        assert (cpu["profile"], cpu["splat_steps"], cpu["splat_max_width"], cpu["splat_time_budget_s"]) == (
            "cpu", 3000, 400, 300.0,
        )  # fmt: skip
        disp.offers = "gpu"
        offered = {p["name"]: p["offered"] for p in c.get("/options").json()["profiles"]}
        assert offered == {"cpu": False, "gpu": True}
        gpu = create({"seed": 5})
        assert (gpu["profile"], gpu["splat_steps"], gpu["views_per_ground_image"], gpu["seed"]) == (
            "gpu",
            7000,
            4,
            5,
        )
        named = create({"profile": "cpu", "max_keypoints": 2048})
        assert (named["profile"], named["splat_steps"], named["max_keypoints"]) == ("cpu", 3000, 2048)
        mixed = create({"splat_steps": 1234})
        assert (mixed["profile"], mixed["splat_steps"], mixed["splat_max_width"]) == ("gpu", 1234, 1600)
        r = c.post(f"/projects/{pid}/jobs", json={"options": {"profile": "tpu"}}, headers=t.headers)
        assert r.status_code == 422 and "profile" in r.text
    finally:
        disp.offers = "cpu"


def test_job_create_validation_and_preconditions(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = _ready_project(api_env, t, make_jpeg)
    bad = {
        "views_per_ground_image": 0,
        "matcher": "orb",
        "bogus": True,
        "stages": ["aerial_sfm", "nope"],
        "seed": "x",
    }
    r = c.post(f"/projects/{pid}/jobs", json={"options": bad}, headers=t.headers)
    assert r.status_code == 422
    fields = {tuple(e["loc"][2:3]) for e in r.json()["detail"]}
    assert {("views_per_ground_image",), ("matcher",), ("bogus",), ("stages",), ("seed",)} <= fields
    assert (
        c.post(f"/projects/{pid}/jobs", json={"options": {"stages": []}}, headers=t.headers).status_code
        == 422
    )
    assert c.post(f"/projects/{pid}/jobs", json={"opts": {}}, headers=t.headers).status_code == 422
    assert api_env.dispatcher.calls == [] or all(call[1] != pid for call in api_env.dispatcher.calls)

    empty = new_project(api_env, t)
    r = c.post(f"/projects/{empty}/jobs", json={}, headers=t.headers)
    assert r.status_code == 409 and "no aerial images" in r.json()["detail"]
    no_pos = _ready_project(api_env, t, make_jpeg, pos=False)
    r = c.post(f"/projects/{no_pos}/jobs", json={}, headers=t.headers)
    assert r.status_code == 409 and "no POS" in r.json()["detail"]
    no_ground = _ready_project(api_env, t, make_jpeg, ground=False)
    r = c.post(f"/projects/{no_ground}/jobs", json={}, headers=t.headers)
    assert r.status_code == 409 and "ground" in r.json()["detail"]
    only_aerial = {"options": {"stages": ["train_splat", "aerial_sfm"]}}
    r = c.post(f"/projects/{no_ground}/jobs", json=only_aerial, headers=t.headers)
    assert r.status_code == 201 and r.json()["options"]["stages"] == ["aerial_sfm", "train_splat"]
    # what would fail minutes later fails now: too few aerial images, images without POS, no intrinsics
    two = _ready_project(api_env, t, make_jpeg, aerial=2)
    r = c.post(f"/projects/{two}/jobs", json={}, headers=t.headers)
    assert r.status_code == 409 and "at least 3" in r.json()["detail"]
    partial = _ready_project(api_env, t, make_jpeg, pos=False)
    r = c.post(
        f"/projects/{partial}/pos",
        files={"file": ("p.csv", pos_csv(["aerial/A1.jpg", "aerial/A2.jpg", "aerial/A3.jpg"]))},
        headers=t.headers,
    )
    assert r.status_code == 200
    r = c.post(f"/projects/{partial}/jobs", json={}, headers=t.headers)
    assert r.status_code == 409 and "1 image(s) have no POS row: ground/G1.jpg" in r.json()["detail"]
    no_cams = _ready_project(api_env, t, make_jpeg, cameras=False)
    r = c.post(f"/projects/{no_cams}/jobs", json={}, headers=t.headers)
    assert r.status_code == 409 and "no intrinsics for the aerial images" in r.json()["detail"]
    assert "no EXIF focal length" in r.json()["detail"]
    with api_env.session() as s:
        assert [crud.list_jobs(s, p) for p in (two, partial, no_cams)] == [[], [], []]
    r = c.post(f"/projects/{pid}/jobs", headers=t.headers)  # no body: every default
    assert r.status_code == 201 and r.json()["options"]["stages"][-1] == "combined_sfm"
    assert r.json()["options"]["out_crs"] is None
    r = c.post(f"/projects/{pid}/jobs", json={"options": {"out_crs": "EPSG:999999"}}, headers=t.headers)
    assert r.status_code == 422 and "unknown CRS" in r.text
    sweref = _ready_project(api_env, t, make_jpeg, crs="EPSG:3006")  # the project's CRS is the default
    r = c.post(f"/projects/{sweref}/jobs", json={}, headers=t.headers)
    assert r.status_code == 201 and r.json()["options"]["out_crs"] == "EPSG:3006"
    r = c.post(f"/projects/{sweref}/jobs", json={"options": {"out_crs": "EPSG:32633"}}, headers=t.headers)
    assert r.json()["options"]["out_crs"] == "EPSG:32633"


def test_job_create_status_cancel_rerun(api_env, make_jpeg) -> None:
    c, t, disp = api_env.client, api_env.tenant(), api_env.dispatcher
    pid = _ready_project(api_env, t, make_jpeg)
    opts = {"matcher": "sift", "views_per_ground_image": 8, "stages": ["aerial_sfm", "train_splat", "reduce"]}
    r = c.post(f"/projects/{pid}/jobs", json={"options": opts}, headers=t.headers)
    assert r.status_code == 201, r.text
    job = r.json()
    jid = job["id"]
    assert job["status"] == "queued" and job["progress"] == 0 and job["attempt"] == 1
    assert job["options"]["matcher"] == "sift" and job["options"]["max_keypoints"] == 1024  # the cpu profile
    assert disp.calls[-1] == ("submit", jid, None)
    assert [j["id"] for j in c.get(f"/projects/{pid}/jobs", headers=t.headers).json()] == [jid]

    with api_env.session() as s:  # a worker reports
        run = crud.start_stage(s, jid, "aerial_sfm", worker="w1")
        crud.update_job_progress(s, jid, 0.25)
        crud.finish_stage(s, run)
        crud.update_job_results(s, jid, metrics={"registered": 2})
        s.commit()
    st = c.get(f"/jobs/{jid}", headers=t.headers).json()
    assert st["status"] == "running" and st["current_stage"] == "aerial_sfm"
    assert st["progress_percent"] == 25.0 and "aerial_sfm" in st["timings"]
    assert st["metrics"] == {"registered": 2} and st["started_at"]
    assert [(s["stage"], s["status"], s["worker"]) for s in st["stages"]] == [
        ("aerial_sfm", "succeeded", "w1")
    ]

    r = c.post(f"/jobs/{jid}/rerun", json={}, headers=t.headers)
    assert r.status_code == 409  # still running
    r = c.post(f"/jobs/{jid}/cancel", headers=t.headers)
    assert r.status_code == 200 and r.json()["status"] == "cancelled" and r.json()["finished_at"]
    assert disp.calls[-1] == ("revoke", jid)
    n_calls = len(disp.calls)
    assert c.post(f"/jobs/{jid}/cancel", headers=t.headers).status_code == 200  # idempotent
    assert len(disp.calls) == n_calls

    r = c.post(f"/jobs/{jid}/rerun", json={"from_stage": "plan_views"}, headers=t.headers)
    assert r.status_code == 422  # not one of this job's stages
    r = c.post(f"/jobs/{jid}/rerun", json={"from_stage": "warp"}, headers=t.headers)
    assert r.status_code == 422
    r = c.post(f"/jobs/{jid}/rerun", json={"from_stage": "train_splat"}, headers=t.headers)
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "queued" and r.json()["attempt"] == 2 and r.json()["progress"] == 0
    assert r.json()["force_from"] is None
    assert disp.calls[-1] == ("submit", jid, "train_splat")
    assert len(c.get(f"/jobs/{jid}", headers=t.headers).json()["stages"]) == 1  # history kept

    with api_env.session() as s:
        crud.set_job_status(s, jid, JobStatus.failed, error="boom")
        s.commit()
    assert c.post(f"/jobs/{jid}/cancel", headers=t.headers).status_code == 409  # failed is final
    r = c.post(f"/jobs/{jid}/rerun", json={"force": True}, headers=t.headers)  # forced, from the start
    assert r.status_code == 200 and r.json()["force_from"] == "aerial_sfm" and r.json()["attempt"] == 3
    with api_env.session() as s:
        crud.set_job_status(s, jid, JobStatus.failed, error="boom")
        s.commit()
    assert c.post(f"/jobs/{jid}/rerun", headers=t.headers).status_code == 200  # no body: from the start
    assert disp.calls[-1] == ("submit", jid, None)
    assert c.get(f"/jobs/{jid}", headers=t.headers).json()["force_from"] is None  # not forced this time

    disp.fail = RuntimeError("broker unreachable")
    try:
        r = c.post(f"/projects/{pid}/jobs", json={}, headers=t.headers)
    finally:
        disp.fail = None
    assert r.status_code == 503 and "broker unreachable" in r.json()["detail"]
    failed = [j for j in c.get(f"/projects/{pid}/jobs", headers=t.headers).json() if j["id"] != jid]
    assert failed[0]["status"] == "failed" and "dispatch failed" in failed[0]["error"]
    assert c.get(f"/jobs/{uuid.uuid4()}", headers=t.headers).status_code == 404


def test_errors_are_json(api_env) -> None:
    t = api_env.tenant()
    r = api_env.client.get("/projects/does-not-exist", headers=t.headers)
    assert r.status_code == 404 and r.json() == {"detail": "project does-not-exist not found"}
    r = api_env.client.post(
        "/projects", content=b"{not json", headers={**t.headers, "Content-Type": "application/json"}
    )
    assert r.status_code == 422 and isinstance(r.json()["detail"], list)
    r = api_env.client.get("/nowhere")
    assert r.status_code == 404 and "detail" in r.json()


def test_camera_intrinsics_round_trip_and_validation(api_env) -> None:
    client, tenant = api_env.client, api_env.tenant()
    headers = tenant.headers
    url = f"/projects/{new_project(api_env, tenant)}/cameras"
    assert client.get(url, headers=headers).status_code == 404
    good = {"aerial": {"model": "PINHOLE", "width": 1600, "height": 1200, "params": [1300, 1300, 800, 600]}}
    r = client.put(url, json=good, headers=headers)
    assert r.status_code == 200, r.text
    assert client.get(url, headers=headers).json() == good
    for bad in (
        {"aerial": {"model": "PINHOLE", "width": 1600, "height": 1200, "params": [1300, 800, 600]}},
        {"aerial": {"model": "FISHEYE_X", "width": 1600, "height": 1200, "params": [1300]}},
        {"aerial": {"model": "PINHOLE", "width": 0, "height": 1200, "params": [1300, 1300, 800, 600]}},
        {"air": good["aerial"]},
        {},
    ):
        assert client.put(url, json=bad, headers=headers).status_code == 422, bad
    assert client.get(url, headers=headers).json() == good  # the bad requests left it untouched
    assert client.get(url, headers=api_env.tenant().headers).status_code == 404  # another tenant


def test_a_jobs_inputs_are_frozen_while_it_runs(api_env, make_jpeg) -> None:
    """A job snapshots its images and POS: deleting an image it uses, or replacing the POS or the
    intrinsics, is 409 while it is queued or running (nothing is lost); once it has ended they may
    change, and a rerun on changed inputs is 409 with what changed."""
    c, t = api_env.client, api_env.tenant()
    pid = _ready_project(api_env, t, make_jpeg)
    jid = c.post(f"/projects/{pid}/jobs", json={}, headers=t.headers).json()["id"]
    with api_env.session() as s:
        snap = crud.get_job(s, jid).inputs
    assert sorted(snap["images"]) == ["aerial/A1.jpg", "aerial/A2.jpg", "aerial/A3.jpg", "ground/G1.jpg"]
    before = snapshot(api_env, t, pid)
    r = c.delete(f"/projects/{pid}/images/aerial/A2.jpg", headers=t.headers)
    assert r.status_code == 409 and jid in r.json()["detail"]
    pos = pos_csv(["aerial/A1.jpg", "aerial/A2.jpg", "aerial/A3.jpg", "ground/G1.jpg"], lat=56.0)
    assert (
        c.post(f"/projects/{pid}/pos", files={"file": ("p.csv", pos)}, headers=t.headers).status_code == 409
    )
    cam = {"model": "PINHOLE", "width": 64, "height": 48, "params": [61.0, 61.0, 32.0, 24.0]}
    assert c.put(f"/projects/{pid}/cameras", json={"aerial": cam}, headers=t.headers).status_code == 409
    assert snapshot(api_env, t, pid) == before
    # an image uploaded meanwhile is not the job's
    assert upload(api_env, t, pid, {"A9.jpg": make_jpeg(seed=9)}).status_code == 201
    assert c.delete(f"/projects/{pid}/images/aerial/A9.jpg", headers=t.headers).status_code == 204

    with api_env.session() as s:  # the job ends
        crud.set_job_status(s, jid, JobStatus.running)
        crud.set_job_status(s, jid, JobStatus.succeeded)
        s.commit()
    assert c.delete(f"/projects/{pid}/images/aerial/A2.jpg", headers=t.headers).status_code == 204
    r = c.post(f"/jobs/{jid}/rerun", json={}, headers=t.headers)
    assert r.status_code == 409 and "image aerial/A2.jpg was deleted" in r.json()["detail"]
