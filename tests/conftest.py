"""Shared fixtures."""

import os

# One thread for pycolmap, torch and numba in every test: pycolmap's multi-threaded bundle adjustment
# differs in the last bits from run to run, and on the tiny scenes of the tests that can change which
# images register, which views are planned and whether any match is transferred. Tests that need
# another value set MIDVIEW_NUM_THREADS themselves.
os.environ.setdefault("MIDVIEW_NUM_THREADS", "1")

from servers import postgres_server, postgres_url, redis_url, s3_server  # noqa: F401

# ---------------------------------------------------------------------------------------------------------
# API fixtures (tests/test_api*.py): one app per backend and test module (SQLite + local storage,
# PostgreSQL + SeaweedFS S3), a fresh tenant per test so that tests never see each other's rows or objects.
API_BACKENDS = ("sqlite-local", "postgres-s3")

import pytest  # noqa: E402

from api.config import ApiSettings  # noqa: E402


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The synthetic `tiny` preset (seed 0), rendered once per session; tests only read it (a test
    module may define its own `tiny_scene` with another configuration)."""
    from services.synth import confs, main

    return main(confs["tiny"], tmp_path_factory.mktemp("tiny") / "scene", seed=0)


class RecordingDispatcher:
    """Records submit/revoke instead of queueing work. The API layer is tested alone: tests inject this
    with `app.dependency_overrides[api.deps.get_dispatcher]`; the Celery and embedded dispatchers are
    tested with the workers."""

    def __init__(self):
        self.calls = []
        self.fail = None  # an exception for submit to raise (dispatch failures)
        self.offers = "cpu"  # the job profile its (imagined) workers offer

    def profile(self):
        return self.offers

    def submit(self, job_id, from_stage=None):
        if self.fail is not None:
            raise self.fail
        self.calls.append(("submit", job_id, from_stage))
        return None

    def revoke(self, job_id):
        self.calls.append(("revoke", job_id))


class ApiEnv:
    """An app on one backend, its TestClient and what tests need to look behind the API."""

    def __init__(self, kind, app, client, dispatcher):
        self.kind, self.app, self.client, self.dispatcher = kind, app, client, dispatcher
        self.settings = app.state.settings
        self.storage = app.state.storage

    @property
    def s3(self):
        return self.kind == "postgres-s3"

    def session(self):
        return self.app.state.sessionmaker()

    def tenant(self, name=None):
        """A new tenant: an object with id, key and headers (the bearer Authorization)."""
        import types
        import uuid

        from api.bootstrap import create_tenant_with_key
        from shared.db import crud

        name = name or f"tenant-{uuid.uuid4().hex[:10]}"
        with self.session() as s:
            key = create_tenant_with_key(s, name, pepper=self.settings.api_key_pepper)
            tenant_id = crud.get_api_key(s, key, pepper=self.settings.api_key_pepper).tenant_id
            s.commit()
        return types.SimpleNamespace(id=tenant_id, key=key, headers={"Authorization": f"Bearer {key}"})


def make_api_settings(kind, folder, request, **overrides):
    """ApiSettings of a backend kind ("sqlite-local" or "postgres-s3") with its data under folder."""
    from shared.db.session import upgrade_database

    # the tests' webhook receivers listen on 127.0.0.1, which the service refuses unless allowed
    common = dict(
        data_dir=folder,
        events_poll_s=0.05,
        upload_tmp_dir=str(folder),
        upload_part_size=5 << 20,
        webhook_allow_networks="127.0.0.1/32",
    )
    common.update(overrides)
    if kind == "sqlite-local":
        url = f"sqlite:///{folder / 'midview.db'}"
        upgrade_database(url)
        return ApiSettings(database_url=url, storage="local", storage_root=folder / "storage", **common)
    s3 = request.getfixturevalue("s3_server")
    url = request.getfixturevalue("postgres_server").create_database()
    upgrade_database(url)
    return ApiSettings(
        database_url=url,
        storage="s3",
        s3_endpoint_url=s3.endpoint_url,
        s3_bucket=s3.bucket,
        s3_region=s3.region,
        s3_access_key=s3.access_key,
        s3_secret_key=s3.secret_key,
        **common,
    )


@pytest.fixture(scope="module", params=API_BACKENDS)
def api_env(request, tmp_path_factory):
    """The API on each backend (module-wide; tests make their own tenants)."""
    from fastapi.testclient import TestClient

    from api import deps
    from api.main import create_app

    settings = make_api_settings(request.param, tmp_path_factory.mktemp("api"), request)
    app = create_app(settings)
    dispatcher = RecordingDispatcher()
    app.dependency_overrides[deps.get_dispatcher] = lambda: dispatcher
    with TestClient(app) as client:
        yield ApiEnv(request.param, app, client, dispatcher)


def _jpeg(width=64, height=48, seed=0, padding=0):
    """A real JPEG (a smooth random pattern); padding adds that many bytes of COM segments."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (max(2, height // 8), max(2, width // 8), 3), dtype=np.uint8)
    img = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    data = buf.tobytes()
    segments = []
    while padding > 0:
        n = min(padding, 65533)
        segments.append(b"\xff\xfe" + (n + 2).to_bytes(2, "big") + bytes([seed % 251 + 1]) * n)
        padding -= n
    return data[:2] + b"".join(segments) + data[2:]


@pytest.fixture
def make_jpeg():
    """make_jpeg(width=64, height=48, seed=0, padding=0) -> JPEG bytes."""
    return _jpeg


# ---------------------------------------------------------------------------------------------------------
# Workers (tests/test_workers.py, tests/test_service_e2e.py): the service on PostgreSQL + SeaweedFS + Redis
# with a real Celery worker process, and the synthetic `tiny` survey it works on.


@pytest.fixture(scope="session")
def tiny_survey(tmp_path_factory):
    """The synthetic `tiny` preset (seed 0): images/{aerial,ground}, pos.csv, cameras.json, gt/."""
    from services import synth

    return synth.main(synth.confs["tiny"], tmp_path_factory.mktemp("survey") / "tiny", seed=0)


@pytest.fixture(scope="session")
def service_settings(request, tmp_path_factory):
    """ApiSettings of the distributed service: a fresh migrated PostgreSQL database, the SeaweedFS
    bucket, the test Redis db as Celery broker and result backend, dispatcher celery."""
    from shared.db.session import upgrade_database

    s3 = request.getfixturevalue("s3_server")
    broker = request.getfixturevalue("redis_url")
    folder = tmp_path_factory.mktemp("service")
    url = request.getfixturevalue("postgres_server").create_database()
    upgrade_database(url)
    return ApiSettings(
        data_dir=folder / "api",
        work_dir=folder / "work-api",
        upload_tmp_dir=str(folder),
        database_url=url,
        storage="s3",
        s3_endpoint_url=s3.endpoint_url,
        s3_bucket=s3.bucket,
        s3_region=s3.region,
        s3_access_key=s3.access_key,
        s3_secret_key=s3.secret_key,
        broker_url=broker,
        result_backend=broker,
        dispatcher="celery",
        num_threads=1,
        events_poll_s=0.05,
        webhook_allow_networks="127.0.0.1/32",
    )


def worker_environment(settings, work_dir):
    """os.environ plus the MIDVIEW_* variables that give a worker process these settings."""
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("MIDVIEW_")}
    values = {
        "DATA_DIR": settings.data_dir,
        "WORK_DIR": work_dir,
        "DATABASE_URL": settings.database_url,
        "STORAGE": settings.storage,
        "STORAGE_ROOT": settings.storage_root,
        "S3_ENDPOINT_URL": settings.s3_endpoint_url,
        "S3_BUCKET": settings.s3_bucket,
        "S3_REGION": settings.s3_region,
        "S3_ACCESS_KEY": settings.s3_access_key,
        "S3_SECRET_KEY": settings.s3_secret_key,
        "BROKER_URL": settings.broker_url,
        "RESULT_BACKEND": settings.result_backend,
        "NUM_THREADS": settings.num_threads,
        "TASK_MAX_RETRIES": settings.task_max_retries,
        "WEBHOOK_ALLOW_NETWORKS": settings.webhook_allow_networks,
        "LOG_LEVEL": "INFO",
    }
    env.update({f"MIDVIEW_{k}": str(v) for k, v in values.items() if v is not None})
    env["PYTHONUNBUFFERED"] = "1"
    env["OMP_NUM_THREADS"] = "1"
    return env


def settings_environment(settings):
    """os.environ without its MIDVIEW_* variables, plus MIDVIEW_<FIELD> for every field of settings that
    is not None: the Settings (ApiSettings) of a process started with it equal these (an API process)."""
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("MIDVIEW_")}
    values = settings.model_dump()
    env.update({f"MIDVIEW_{k.upper()}": str(v) for k, v in values.items() if v is not None})
    env["PYTHONUNBUFFERED"] = "1"
    env["OMP_NUM_THREADS"] = "1"
    return env


@pytest.fixture(scope="module")
def api_server(service_settings, tmp_path_factory):
    """The API with service_settings (Celery dispatcher) in a uvicorn process: an object with base_url
    (http://127.0.0.1:PORT), proc and log; stopped at the end of the module."""
    from servers import start_uvicorn

    log = tmp_path_factory.mktemp("uvicorn") / "uvicorn.log"
    server = start_uvicorn(settings_environment(service_settings), log)
    try:
        yield server
    finally:
        server.stop()


class CeleryWorkerProcess:
    """A `celery worker` subprocess of the test service (its log in `log`)."""

    def __init__(self, proc, log, work_dir, hostname):
        self.proc, self.log, self.work_dir, self.hostname = proc, log, work_dir, hostname

    def text(self):
        return self.log.read_text(errors="replace")

    def alive(self):
        return self.proc.poll() is None


@pytest.fixture(scope="session")
def celery_worker(service_settings, tmp_path_factory):
    """A real Celery worker (prefork, one process) consuming gpu, cpu and reduce, started once."""
    import sys
    import time
    import uuid
    from pathlib import Path

    from servers import _spawn, _stop, _tail

    folder = tmp_path_factory.mktemp("celery-worker")
    hostname = f"midview-test-{uuid.uuid4().hex[:6]}@%h"
    log = folder / "worker.log"
    from workers.celery_app import QUEUES

    args = [sys.executable, "-m", "celery", "-A", "workers.celery_app", "worker", "-Q", ",".join(QUEUES),
            "-c", "1", "-P", "prefork", "-l", "INFO", "-n", hostname,
            "--without-gossip", "--without-mingle", "--without-heartbeat"]  # fmt: skip
    root = Path(__file__).resolve().parents[1]
    proc = _spawn(args, log, cwd=root, env=worker_environment(service_settings, folder / "work"))
    deadline = time.monotonic() + 60
    while "ready." not in (log.read_text(errors="replace") if log.exists() else ""):
        if proc.poll() is not None or time.monotonic() > deadline:
            _stop(proc)
            pytest.fail(f"the Celery worker did not start:\n{_tail(log, 4000)}")
        time.sleep(0.2)
    try:
        yield CeleryWorkerProcess(proc, log, folder / "work", hostname)
    finally:
        _stop(proc, timeout=15)


def new_tenant(app, prefix="t"):
    """A new tenant of the app's database and its API key: SimpleNamespace(id, headers)."""
    import types
    import uuid

    from api.bootstrap import create_tenant_with_key
    from shared.db import crud

    with app.state.sessionmaker() as s:
        key = create_tenant_with_key(s, f"{prefix}-{uuid.uuid4().hex[:8]}")
        tenant_id = crud.get_api_key(s, key).tenant_id
        s.commit()
    return types.SimpleNamespace(id=tenant_id, headers={"Authorization": f"Bearer {key}"})


def jobbable_project(client, headers, make_jpeg, ground=True, aerial=3, name=None):
    """A project a job can be created on: `aerial` aerial images (and one ground image), a POS row for
    each, and a cameras.json for both sets (the test images carry no EXIF). Returns its id."""
    import uuid

    pid = client.post(
        "/projects", json={"name": name or f"p-{uuid.uuid4().hex[:8]}"}, headers=headers
    ).json()["id"]
    sets = [("aerial", [f"A{i + 1}.jpg" for i in range(aerial)])] + (
        [("ground", ["G1.jpg"])] if ground else []
    )
    names = []
    for k, (image_set, files) in enumerate(sets):
        parts = [("files", (f, make_jpeg(seed=10 * k + i), "image/jpeg")) for i, f in enumerate(files)]
        r = client.post(f"/projects/{pid}/images", params={"set": image_set}, files=parts, headers=headers)
        assert r.status_code == 201, r.text
        names += [f"{image_set}/{f}" for f in files]
    rows = "".join(f"{n},{55.7 + i * 1e-4:.7f},13.19,{100 + i:.2f}\n" for i, n in enumerate(names))
    r = client.post(
        f"/projects/{pid}/pos", files={"file": ("pos.csv", "name,lat,lon,h\n" + rows)}, headers=headers
    )
    assert r.status_code == 200, r.text
    cam = {"model": "PINHOLE", "width": 64, "height": 48, "params": [60.0, 60.0, 32.0, 24.0]}
    r = client.put(f"/projects/{pid}/cameras", json={"aerial": cam, "ground": cam}, headers=headers)
    assert r.status_code == 200, r.text
    return pid


def upload_survey(client, tenant, scene, storage, name=None, cameras=True):
    """Create a project of tenant (id, headers) and upload a survey folder over HTTP (images of both
    sets, pos.csv, cameras.json). `storage` is unused (kept for callers). Returns the project id."""
    import json
    import uuid

    headers = tenant.headers
    r = client.post("/projects", json={"name": name or f"survey-{uuid.uuid4().hex[:8]}"}, headers=headers)
    assert r.status_code == 201, r.text
    project = r.json()
    for image_set in ("aerial", "ground"):
        files = [
            ("files", (p.name, p.read_bytes(), "image/jpeg"))
            for p in sorted((scene / "images" / image_set).iterdir())
        ]
        r = client.post(f"/projects/{project['id']}/images?set={image_set}", files=files, headers=headers)
        assert r.status_code in (200, 201), r.text
    pos = (scene / "pos.csv").read_bytes()
    r = client.post(f"/projects/{project['id']}/pos", files={"file": ("pos.csv", pos)}, headers=headers)
    assert r.status_code == 200, r.text
    if cameras:
        body = json.loads((scene / "cameras.json").read_text())
        r = client.put(f"/projects/{project['id']}/cameras", json=body, headers=headers)
        assert r.status_code == 200, r.text
    return project["id"]


def wait_for_job(client, headers, job_id, timeout_s, seen=None):
    """Poll GET /jobs/{id} until a final status; returns the job; `seen` collects (status, stage,
    progress) snapshots."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        job = client.get(f"/jobs/{job_id}", headers=headers).json()
        if seen is not None:
            seen.append((job["status"], job["current_stage"], job["progress"]))
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job
        if time.monotonic() > deadline:
            raise AssertionError(f"job {job_id} not finished after {timeout_s} s: {job}")
        time.sleep(0.5)


def pytest_collection_modifyitems(config, items):
    """The modules with a slow test first, the others after them, each in its own order: scripts/test.sh
    runs the suite on pytest-xdist workers a module at a time (--dist loadfile --no-loadscope-reorder), so
    every worker starts on one of the end-to-end modules and the quick ones fill in around them."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)
