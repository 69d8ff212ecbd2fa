"""Shared fixtures."""

from servers import postgres_server, postgres_url, redis_url, s3_server  # noqa: F401

# ---------------------------------------------------------------------------------------------------------
# API fixtures (tests/test_api*.py): one app per backend and test module (SQLite + local storage,
# PostgreSQL + SeaweedFS S3), a fresh tenant per test so that tests never see each other's rows or objects.
API_BACKENDS = ("sqlite-local", "postgres-s3")

import pytest  # noqa: E402

from api.config import ApiSettings  # noqa: E402


class RecordingDispatcher:
    """Records submit/revoke instead of queueing work. The API layer is tested alone: tests inject this
    with `app.dependency_overrides[api.deps.get_dispatcher]`; the Celery and embedded dispatchers are
    tested with the workers."""

    def __init__(self):
        self.calls = []
        self.fail = None  # an exception for submit to raise (dispatch failures)

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

    common = dict(data_dir=folder, events_poll_s=0.05, upload_tmp_dir=str(folder), upload_part_size=5 << 20)
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
