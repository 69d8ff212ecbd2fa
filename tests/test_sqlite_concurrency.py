"""The embedded service (SQLite) under concurrent writes: API requests that write while a worker
commits progress get no "database is locked" (they wait for the write lock instead of failing)."""

from __future__ import annotations

import threading
import uuid
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

from conftest import ApiEnv, jobbable_project
from fastapi.testclient import TestClient

from api import deps
from api.config import ApiSettings
from api.main import create_app
from shared.db import crud
from shared.db.models import JobStatus
from shared.db.session import make_engine, make_sessionmaker, upgrade_database


class _Dispatcher:
    def submit(self, *args, **kwargs):
        return None

    def revoke(self, *args):
        pass


def test_api_writes_while_the_worker_commits(tmp_path, make_jpeg):
    url = f"sqlite:///{tmp_path / 'midview.db'}"
    upgrade_database(url)
    settings = ApiSettings(
        data_dir=tmp_path,
        database_url=url,
        storage="local",
        storage_root=tmp_path / "s",
        rate_limit_per_minute=0,
    )
    app = create_app(settings)
    app.dependency_overrides[deps.get_dispatcher] = lambda: _Dispatcher()
    with TestClient(app, raise_server_exceptions=False) as c:
        h = ApiEnv("sqlite-local", app, c, None).tenant().headers
        pid = jobbable_project(c, h, make_jpeg)
        jid = c.post(f"/projects/{pid}/jobs", json={}, headers=h).json()["id"]
        stop, errors, updates = threading.Event(), [], [0]

        def worker() -> None:  # what the in-process worker does: stage runs and progress, committed
            sm = make_sessionmaker(make_engine(url))
            with sm() as s:
                crud.set_job_status(s, jid, JobStatus.running)
                s.commit()
            while not stop.is_set():
                try:
                    with sm() as s:
                        run = crud.start_stage(s, jid, "aerial_sfm", worker="w")
                        s.commit()
                        for k in range(10):
                            crud.update_job_progress(s, jid, k / 10)
                            s.commit()
                            updates[0] += 1
                        crud.finish_stage(s, run)
                        s.commit()
                except Exception as e:  # noqa: BLE001 - counted, the test fails on any
                    errors.append(repr(e))

        def write(i: int) -> tuple[int, int]:
            k = i % 4
            if k == 0:
                r = c.post("/projects", json={"name": f"p{i}-{uuid.uuid4().hex[:6]}"}, headers=h)
            elif k == 1:
                r = c.post(f"/projects/{pid}/jobs", json={}, headers=h)
            elif k == 2:
                r = c.post("/webhooks", json={"url": "https://hooks.example.com/x"}, headers=h)
            else:
                r = c.get(f"/jobs/{jid}", headers=h)
            return k, r.status_code

        th = threading.Thread(target=worker)
        th.start()
        try:
            with ThreadPoolExecutor(8) as ex:
                codes = Counter(ex.map(write, range(240)))
        finally:
            stop.set()
            th.join()
    assert codes == Counter({(0, 201): 60, (1, 201): 60, (2, 201): 60, (3, 200): 60}), codes
    assert errors == [] and updates[0] > 0
