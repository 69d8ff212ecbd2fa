"""The workers (workers/): job folder sync with storage, the reconciler's decisions, the Celery canvas,
error classification, the embedded dispatcher, and one job through a real Celery worker process.

Real servers: SeaweedFS (S3), PostgreSQL, Redis (tests/servers.py); each test skips when its server is
missing."""

from __future__ import annotations

import json
import os
import time
import types
import uuid
from datetime import timedelta
from pathlib import Path

import pytest
import sqlalchemy as sa

from services.pipeline import STAGES
from shared.db import crud
from shared.db.models import Job, JobStatus, StageRun, StageStatus, utcnow
from workers import jobsync

# -- jobsync -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def s3_storage(request):
    from shared.storage import S3Storage

    s3 = request.getfixturevalue("s3_server")
    return S3Storage(
        s3.bucket,
        endpoint_url=s3.endpoint_url,
        region=s3.region,
        access_key=s3.access_key,
        secret_key=s3.secret_key,
    )


def _write(path: Path, data: bytes, mtime_ns: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    os.utime(path, ns=(mtime_ns, mtime_ns))


def test_push_pull_round_trip_by_content_and_skips_unchanged(s3_storage, tmp_path):
    prefix = f"tenants/t/projects/p/jobs/{uuid.uuid4()}/"
    a, b = tmp_path / "a", tmp_path / "b"
    t0 = 1_700_000_000_123_456_789
    files = {
        "sfm/sparse/cameras.bin": b"cameras" * 10,
        "sfm/report.json": b'{"NRI": "4/4"}',
        "splat/point_cloud.ply": os.urandom(70_000),
        "splat/ckpts/step_100.pt": b"checkpoint",  # local only: never pushed
        "stages/aerial_sfm.json": b"{}",
    }
    for i, (rel, data) in enumerate(files.items()):
        _write(a / rel, data, t0 + i * 1_000_000_007)
    (a / "sfm" / ".scratch").write_bytes(b"hidden")  # dot files stay local

    st = jobsync.push(s3_storage, prefix, a, ["sfm", "stages/aerial_sfm.json"], "aerial_sfm", mirror=["sfm"])
    assert sorted(st.transferred) == ["sfm/report.json", "sfm/sparse/cameras.bin", "stages/aerial_sfm.json"]
    st = jobsync.push(s3_storage, prefix, a, ["splat"], "train_splat", mirror=["splat"])
    assert st.transferred == ["splat/point_cloud.ply"]
    assert jobsync.push(s3_storage, prefix, a, ["sfm"], "aerial_sfm").transferred == []  # unchanged
    keys = s3_storage.list(prefix)
    assert f"{prefix}manifests/aerial_sfm.json" in keys and not any(
        "ckpts" in k or ".scratch" in k for k in keys
    )

    # another worker: every file, byte for byte
    st = jobsync.pull(s3_storage, prefix, b)
    assert len(st.transferred) == 4 and st.skipped == 0
    for rel, data in files.items():
        if "ckpts" in rel:
            assert not (b / rel).exists()
            continue
        assert (b / rel).read_bytes() == data
    st = jobsync.pull(s3_storage, prefix, b)
    assert st.transferred == [] and st.skipped == 4
    # the content decides, not the time: a file touched here (same bytes) is not fetched again
    os.utime(b / "sfm" / "report.json", ns=(t0 + 7, t0 + 7))
    st = jobsync.pull(s3_storage, prefix, b)
    assert st.transferred == [] and st.skipped == 4

    # a changed file comes again; a file removed from a mirrored folder is deleted here too
    _write(a / "sfm" / "report.json", b'{"NRI": "3/4"}', t0 + 99)
    (a / "sfm" / "sparse" / "cameras.bin").unlink()
    st = jobsync.push(s3_storage, prefix, a, ["sfm"], "aerial_sfm", mirror=["sfm"])
    assert st.transferred == ["sfm/report.json"] and st.deleted == ["sfm/sparse/cameras.bin"]
    (b / "local-scratch.txt").write_text("never in storage")
    st = jobsync.pull(s3_storage, prefix, b)
    assert st.transferred == ["sfm/report.json"] and st.deleted == ["sfm/sparse/cameras.bin"]
    assert (b / "sfm" / "report.json").read_bytes() == b'{"NRI": "3/4"}'
    assert not (b / "sfm" / "sparse" / "cameras.bin").exists() and (b / "local-scratch.txt").exists()

    # a file modified locally (same size, other time) is replaced by storage's version
    _write(b / "splat" / "point_cloud.ply", os.urandom(70_000), t0 + 5)
    st = jobsync.pull(s3_storage, prefix, b)
    assert st.transferred == ["splat/point_cloud.ply"]
    assert (b / "splat" / "point_cloud.ply").read_bytes() == files["splat/point_cloud.ply"]


@pytest.fixture(scope="module")
def db_url(request):
    from shared.db.session import upgrade_database

    url = request.getfixturevalue("postgres_server").create_database()
    upgrade_database(url)
    return url


@pytest.fixture(scope="module")
def sessions(db_url):
    from shared.db.session import make_engine, make_sessionmaker

    engine = make_engine(db_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def _project(sessions):
    with sessions() as s:
        tenant = crud.create_tenant(s, f"t-{uuid.uuid4().hex[:8]}")
        project = crud.create_project(s, tenant.id, "p")
        s.commit()
        return tenant.id, project.id


def test_materialize_gives_every_worker_the_same_fingerprints(sessions, s3_storage, tiny_survey, tmp_path):
    """Two workers (two work folders) materialize the same job: same inputs (downloaded at other
    times), so the pipeline's fingerprints, made of contents, agree and a stage done on one is up to
    date on the other."""
    import hashlib

    from services import pipeline
    from services.pos import read_pos_csv
    from shared.storage.keys import image_key_for_name

    tenant_id, project_id = _project(sessions)
    with sessions() as s:
        for image_set in ("aerial", "ground"):
            for p in sorted((tiny_survey / "images" / image_set).iterdir()):
                name = f"{image_set}/{p.name}"
                key = image_key_for_name(tenant_id, project_id, name)
                s3_storage.put_file(key, p)
                data = p.read_bytes()
                crud.add_image(
                    s,
                    project_id,
                    name,
                    sha256=hashlib.sha256(data).hexdigest(),
                    size_bytes=len(data),
                    storage_key=key,
                )
        crud.add_pos_records(s, project_id, read_pos_csv(tiny_survey / "pos.csv"), source_format="csv")
        job = crud.create_job(s, project_id, {"stages": ["aerial_sfm"], "seed": 3})
        s.commit()
        job_id = job.id
    s3_storage.put_bytes(
        jobsync.cameras_key(tenant_id, project_id), (tiny_survey / "cameras.json").read_bytes()
    )

    jobs = []
    for worker in ("w1", "w2"):
        with sessions() as s:
            jobs.append(jobsync.materialize(s, s3_storage, s.get(Job, job_id), tmp_path / worker))
    j1, j2 = jobs
    assert j1.root != j2.root and j1.options.seed == 3
    assert (j1.root / "inputs" / "pos.csv").read_bytes() == (tiny_survey / "pos.csv").read_bytes()
    assert (j1.root / "inputs" / "cameras.json").is_file() and j1.inputs["cameras"]
    sd = pipeline.REGISTRY["aerial_sfm"]
    assert sorted(p.name for p in (j1.image_dir / "aerial").iterdir()) == sorted(
        p.name for p in (tiny_survey / "images" / "aerial").iterdir()
    )
    # the cameras input is an absolute path in the stage conf (services.pipeline): compare the inputs
    fp = [pipeline.fingerprint({}, sd.inputs(j), j.root) for j in jobs]
    assert fp[0] == fp[1]
    # again: nothing downloaded, nothing rewritten (times unchanged)
    before = {p: p.stat().st_mtime_ns for p in (j1.root / "inputs").rglob("*") if p.is_file()}
    with sessions() as s:
        jobsync.materialize(s, s3_storage, s.get(Job, job_id), tmp_path / "w1")
    assert before == {p: p.stat().st_mtime_ns for p in (j1.root / "inputs").rglob("*") if p.is_file()}


# -- reconciler ----------------------------------------------------------------------------------
def _job(s, project_id, status, stage=None, ago_s=3600, root_id=None, stages=None, now=None):
    """A job row whose last sign of life is ago_s before now."""
    job = crud.create_job(s, project_id, {"stages": stages} if stages else {})
    if status != JobStatus.queued:
        crud.set_job_status(s, job, JobStatus.running)
    if stage is not None:
        crud.start_stage(s, job, stage, worker="w").started_at = now - timedelta(seconds=ago_s)
    if status not in (JobStatus.queued, JobStatus.running):
        crud.set_job_status(s, job, status)
        job.finished_at = now - timedelta(seconds=ago_s)
    job.created_at = now - timedelta(seconds=ago_s)
    if job.started_at is not None:
        job.started_at = job.created_at
    job.celery_root_id = root_id
    s.flush()
    return job.id


def test_reconcile_redispatches_what_stalled(sessions):
    from conftest import RecordingDispatcher

    from workers.reconcile import reconcile as run_reconcile

    _, pid = _project(sessions)
    now = utcnow()
    with sessions() as s:
        stalled = _job(s, pid, JobStatus.running, "train_splat", 2000, "root-1", now=now)
        busy = _job(s, pid, JobStatus.running, "render_views", 2000, "root-2", now=now)  # a live task
        fresh = _job(s, pid, JobStatus.running, "aerial_sfm", 60, "root-3", now=now)
        lost = _job(s, pid, JobStatus.queued, None, 2000, None, now=now)  # API died before submit
        waiting = _job(s, pid, JobStatus.queued, None, 2000, "root-5", now=now)  # message in a queue?
        done = _job(s, pid, JobStatus.succeeded, "combined_sfm", 5000, "root-6", now=now)
        other = _job(s, pid, JobStatus.running, "reduce", 2000, None, stages=["reduce"], now=now)
        s.commit()
    mine = {stalled, busy, fresh, lost, waiting, done, other}  # other tests' jobs share the database

    def reconcile(*args, **kw):
        return [a for a in run_reconcile(*args, **kw) if a.job_id in mine]

    # with a liveness probe: every stalled job that no task works on
    d = RecordingDispatcher()
    with sessions() as s:
        actions = reconcile(s, d, now, stall_timeout_s=900, is_live={busy})
        s.commit()
    got = {(a.job_id, a.from_stage) for a in actions}
    assert got == {(stalled, "train_splat"), (lost, None), (waiting, None), (other, "reduce")}, actions
    assert sorted(c for c in d.calls if c[1] in mine) == sorted(("submit", j, f) for j, f in got)

    # without a probe: a queued job with a root task id may still wait in a queue: left alone
    d = RecordingDispatcher()
    with sessions() as s:
        actions = reconcile(s, d, now, 900)
    got = {(a.job_id, a.from_stage) for a in actions}
    assert got == {(stalled, "train_splat"), (busy, "render_views"), (lost, None), (other, "reduce")}
    assert fresh not in {a.job_id for a in actions} and done not in {a.job_id for a in actions}

    # a stage run that finished recently is a sign of life; a failing dispatch is reported, not raised
    live = {busy, fresh, lost, other, waiting}
    d = RecordingDispatcher()
    d.fail = RuntimeError("broker down")
    with sessions() as s:
        run = s.scalar(sa.select(StageRun).where(StageRun.job_id == stalled))
        crud.finish_stage(s, run, StageStatus.succeeded)
        run.finished_at = now - timedelta(seconds=10)
        s.commit()
        assert reconcile(s, d, now, 900, is_live=live) == []
        actions = reconcile(s, d, now + timedelta(seconds=3600), 900, is_live=live)
    assert [a.job_id for a in actions] == [stalled] and "broker down" in actions[0].error


def test_a_message_lost_between_stages_is_dispatched_again_after_the_heartbeat_timeout(sessions):
    """The broker was read (NodeCheck.known) and holds nothing of a job whose stage finished: its next
    message is lost; dispatched again from its current stage after heartbeat_timeout_s, not after
    stall_timeout_s. A job the broker knows, a running stage run and a fresh stage end are left alone."""
    from conftest import RecordingDispatcher

    from workers.reconcile import NodeCheck
    from workers.reconcile import reconcile as run_reconcile

    _, pid = _project(sessions)
    now = utcnow()
    with sessions() as s:
        ids = {}
        for name, ago in (("lost", 45), ("known", 45), ("fresh", 10), ("running", 45)):
            ids[name] = _job(s, pid, JobStatus.running, "aerial_sfm", ago, f"root-{name}", now=now)
            run = s.scalar(sa.select(StageRun).where(StageRun.job_id == ids[name]))
            if name != "running":
                crud.finish_stage(s, run, StageStatus.succeeded)
                run.finished_at = now - timedelta(seconds=ago)
            run.heartbeat_at = now - timedelta(seconds=ago if name != "running" else 5)
        ids["queued"] = _job(s, pid, JobStatus.queued, None, 45, "root-queued", now=now)
        s.commit()
    mine = set(ids.values())
    nodes = NodeCheck(
        ping=lambda names: set(names), heartbeat_timeout_s=30.0, known={ids["known"]}, active={ids["known"]}
    )
    d = RecordingDispatcher()
    with sessions() as s:
        actions = [
            a for a in run_reconcile(s, d, now, 900, is_live={ids["known"]}, nodes=nodes) if a.job_id in mine
        ]
        s.commit()
    got = {(a.job_id, a.from_stage) for a in actions}
    assert got == {(ids["lost"], "aerial_sfm"), (ids["queued"], None)}, actions
    assert all("no task or message of it in the broker" in a.reason for a in actions)
    # without a read of the broker (known None) the stall timeout still rules
    d = RecordingDispatcher()
    with sessions() as s:
        nodes.known = None
        assert [a for a in run_reconcile(s, d, now, 900, nodes=nodes) if a.job_id in mine] == []


def test_redis_liveness_sees_running_and_queued_tasks(redis_url):
    import redis

    from shared.config import Settings
    from workers.celery_app import RUN_STAGE, alive_key, make_app
    from workers.reconcile import RedisLiveness

    r = redis.Redis.from_url(redis_url)
    running, queued, idle = (str(uuid.uuid4()) for _ in range(3))
    r.set(alive_key("some-task"), json.dumps({"job": running, "pid": 1}), ex=30)
    app = make_app(Settings(broker_url=redis_url, result_backend=redis_url), set_as_current=False)
    try:
        app.send_task(RUN_STAGE, args=[queued, "aerial_sfm"], queue="midview-test-liveness")
    finally:
        app.close()
    live = RedisLiveness(r, queues=("midview-test-liveness",)).snapshot()
    assert running in live and queued in live and idle not in live
    r.delete("midview-test-liveness", alive_key("some-task"))


# -- canvas and error policy ---------------------------------------------------------------------
def _sig_view(sig):
    return (sig.task.rsplit(".", 1)[-1], list(sig.args), sig.options.get("queue"), sig.immutable)


def test_canvas_of_a_job():
    from shared.config import Settings
    from workers.celery_app import make_app
    from workers.dispatch import build_canvas

    app = make_app(Settings(broker_url="redis://127.0.0.1:1/0"))
    c = build_canvas(app, "J", list(STAGES))
    after = ["render_views", "match_views", "reduce", "combined_sfm", "splat_all"]
    assert [_sig_view(t) for t in c.tasks] == [
        ("run_stage", ["J", "aerial_sfm"], "gpu", True),
        ("run_stage", ["J", "train_splat"], "gpu", True),
        ("run_stage", ["J", "plan_views"], "gpu", True),
        ("fan_out", ["J", "train_blocks", after], "gpu", True),
    ]
    c = build_canvas(app, "J", ["reduce", "combined_sfm", "splat_all"])
    assert [_sig_view(t) for t in c.tasks] == [
        ("run_stage", ["J", "reduce"], "reduce", True),
        ("run_stage", ["J", "combined_sfm"], "reduce", True),
        ("run_stage", ["J", "splat_all"], "gpu", True),  # the 3DGS of all images: back to a GPU worker
        ("finalize", ["J"], "reduce", True),
    ]
    c = build_canvas(app, "J", ["match_views"])
    assert [_sig_view(t) for t in c.tasks] == [("fan_out", ["J", "match_views", []], "cpu", True)]
    json.dumps(build_canvas(app, "J", list(STAGES)))  # the canvas travels as JSON


def test_fan_out_canvas():
    from workers.tasks import fan_out_canvas

    c = fan_out_canvas("J", "match_views", ["v1", "v2"], "cpu", ["reduce"])
    assert [_sig_view(t) for t in c.tasks] == [
        ("stage_unit", ["J", "match_views", v], "cpu", True) for v in ("v1", "v2")
    ]
    assert [_sig_view(t) for t in c.body.tasks] == [
        ("run_stage", ["J", "match_views"], "cpu", True),
        ("run_stage", ["J", "reduce"], "reduce", True),
        ("finalize", ["J"], "reduce", True),
    ]
    assert [_sig_view(t) for t in fan_out_canvas("J", "match_views", [], "cpu", []).tasks] == [
        ("run_stage", ["J", "match_views"], "cpu", True),
        ("finalize", ["J"], "reduce", True),
    ]
    # blocks on the cpu queue (no GPU), then the views rendered from them and the next fan-out
    c = fan_out_canvas("J", "train_blocks", ["b00", "b01"], "cpu", ["render_views", "match_views", "reduce"])
    assert [_sig_view(t) for t in c.tasks] == [
        ("stage_unit", ["J", "train_blocks", b], "cpu", True) for b in ("b00", "b01")
    ]
    assert [_sig_view(t) for t in c.body.tasks] == [
        ("run_stage", ["J", "train_blocks"], "gpu", True),
        ("run_stage", ["J", "render_views"], "gpu", True),
        ("fan_out", ["J", "match_views", ["reduce"]], "cpu", True),
    ]


def test_route_by_stage():
    from workers.celery_app import FAN_OUT, FINALIZE, RUN_STAGE, STAGE_UNIT, route_task

    assert route_task(RUN_STAGE, ["J", "train_splat"], {}, {}) == {"queue": "gpu"}
    assert route_task(RUN_STAGE, ["J", "reduce"], {}, {}) == {"queue": "reduce"}
    assert route_task(STAGE_UNIT, ["J", "match_views", "v"], {}, {}) == {"queue": "cpu"}
    assert route_task(FAN_OUT, ["J", "train_blocks", []], {}, {}) == {"queue": "gpu"}
    assert route_task(FINALIZE, ["J"], {}, {}) == {"queue": "reduce"}


def test_transient_errors():
    import botocore.exceptions as bx
    import redis
    import sqlalchemy.exc as sx

    from shared.storage import StorageError
    from workers.execute import JobStopped, is_transient

    def wrapped(cause):
        try:
            try:
                raise cause
            except Exception as e:
                raise StorageError("download x") from e
        except StorageError as e:
            return e

    assert is_transient(ConnectionResetError())
    assert is_transient(sx.OperationalError("select", {}, Exception("server closed the connection")))
    assert is_transient(redis.ConnectionError())
    assert is_transient(wrapped(bx.EndpointConnectionError(endpoint_url="http://s3")))
    slow = bx.ClientError({"Error": {"Code": "SlowDown"}, "ResponseMetadata": {"HTTPStatusCode": 503}}, "Get")
    assert is_transient(wrapped(slow))
    missing = bx.ClientError(
        {"Error": {"Code": "NoSuchKey"}, "ResponseMetadata": {"HTTPStatusCode": 404}}, "Get"
    )
    assert not is_transient(wrapped(missing))
    assert not is_transient(FileNotFoundError("sfm/sparse"))
    assert not is_transient(ValueError("bad conf"))
    assert not is_transient(JobStopped("cancelled"))


# -- embedded dispatcher (midview serve) ---------------------------------------------------------
@pytest.mark.slow
def test_embedded_dispatcher_runs_a_job(tiny_survey, tmp_path):
    """`midview serve`'s app (SQLite, local storage, embedded thread) runs a job, a cancel stops one."""
    from conftest import upload_survey, wait_for_job
    from fastapi.testclient import TestClient

    from cli.serve import build_app
    from workers.embedded import EmbeddedDispatcher

    app, key = build_app(tmp_path / "serve", num_threads=1)
    assert key and key.startswith("mv_")
    assert isinstance(app.state.dispatcher, EmbeddedDispatcher)
    headers = {"Authorization": f"Bearer {key}"}
    with TestClient(app) as client:
        with app.state.sessionmaker() as s:
            tenant_id = crud.get_api_key(s, key).tenant_id
        tenant = types.SimpleNamespace(id=tenant_id, headers=headers)
        pid = upload_survey(client, tenant, tiny_survey, app.state.storage)
        t0 = time.monotonic()
        r = client.post(
            f"/projects/{pid}/jobs", json={"options": {"stages": ["aerial_sfm"]}}, headers=headers
        )
        assert r.status_code == 201, r.text
        job = wait_for_job(client, headers, r.json()["id"], 120)
        print(f"embedded aerial_sfm job: {time.monotonic() - t0:.1f} s")
        assert job["status"] == "succeeded", job
        assert [(st["stage"], st["status"]) for st in job["stages"]] == [("aerial_sfm", "succeeded")]
        assert job["metrics"]["aerial_sfm"]["NRI"].endswith("/20")
        names = {a["name"] for a in client.get(f"/jobs/{job['id']}/artifacts", headers=headers).json()}
        assert {"sfm/report.json", "sfm/sparse/images.bin", "cameras.json"} <= names
        # the server kept the stage's log: its progress reports, in order, under the run's heading
        text = client.get(f"/jobs/{job['id']}/log", headers=headers).text
        assert text.startswith("== aerial_sfm (attempt 1, succeeded, "), text[:300]
        reports = [line.split() for line in text.splitlines()[1:]]
        percents = [int(w[2].rstrip("%")) for w in reports if len(w) > 2 and w[1] == "aerial_sfm"]
        assert percents[0] == 0 and percents[-1] == 100 and percents == sorted(percents), text[:2000]
        # rerun: the stage is up to date (same inputs, same times): skipped
        r = client.post(f"/jobs/{job['id']}/rerun", headers=headers)
        job = wait_for_job(client, headers, job["id"], 60)
        assert job["status"] == "succeeded" and job["attempt"] == 2
        assert [st["status"] for st in job["stages"]] == ["succeeded", "skipped"]
        # forced: the stage runs again although it is up to date
        r = client.post(f"/jobs/{job['id']}/rerun", json={"force": True}, headers=headers)
        assert r.status_code == 200, r.text
        job = wait_for_job(client, headers, job["id"], 120)
        assert job["status"] == "succeeded" and job["attempt"] == 3
        assert [st["status"] for st in job["stages"]] == ["succeeded", "skipped", "succeeded"]
        # cancel while it runs: the runner stops at the next report, the job stays cancelled
        opts = {
            "stages": ["aerial_sfm", "train_splat"],
            "splat_steps": 1000,
            "splat_max_width": 240,
            "seed": 1,
        }
        jid = client.post(f"/projects/{pid}/jobs", json={"options": opts}, headers=headers).json()["id"]
        deadline = time.monotonic() + 60
        while client.get(f"/jobs/{jid}", headers=headers).json()["current_stage"] != "train_splat":
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert client.post(f"/jobs/{jid}/cancel", headers=headers).status_code == 200
        assert app.state.dispatcher.wait_idle(60)
        job = client.get(f"/jobs/{jid}", headers=headers).json()
        assert job["status"] == "cancelled"
        assert [(st["stage"], st["status"]) for st in job["stages"]][-1] == ("train_splat", "cancelled")


# -- a real Celery worker ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def service(service_settings, celery_worker):
    from conftest import new_tenant
    from fastapi.testclient import TestClient

    from api.main import create_app

    app = create_app(service_settings)
    with TestClient(app) as client:
        tenant = new_tenant(app, "workers")
        yield types.SimpleNamespace(app=app, client=client, tenant=tenant, worker=celery_worker)


@pytest.mark.slow
def test_a_worker_node_offers_its_device_and_the_api_picks_the_profile_from_it(
    service_settings, celery_worker
):
    """The worker node advertises {device, queues} in Redis (workers.offer); the Celery dispatcher reads
    the profile from the offers: cpu from CPU workers, gpu once a CUDA worker serves the gpu queue."""
    import redis

    from workers.celery_app import QUEUES, redis_url
    from workers.dispatch import CeleryDispatcher
    from workers.offer import OFFER_PREFIX, offer_key, read_offers

    r = redis.Redis.from_url(redis_url(service_settings))
    mine: list[dict] = []
    deadline = time.monotonic() + 90  # the device is probed in a child process (imports torch)
    while not mine and time.monotonic() < deadline:
        mine = [o for o in read_offers(r) if o["hostname"].startswith(celery_worker.hostname.split("@")[0])]
        time.sleep(0.5)
    assert mine and mine[0]["device"] == "cpu" and mine[0]["queues"] == sorted(QUEUES), mine
    assert r.ttl(offer_key(mine[0]["hostname"])) > 0  # a node that dies drops out
    d = CeleryDispatcher(service_settings)
    try:
        assert d.profile() == "cpu"
        fake = f"{OFFER_PREFIX}gpu-test@{uuid.uuid4().hex[:6]}"
        r.set(fake, json.dumps({"device": "cuda", "queues": ["gpu"], "hostname": fake}), ex=30)
        try:
            assert d.profile() == "cpu"  # within its cache
            assert d.profile(max_age_s=0) == "gpu"
        finally:
            r.delete(fake)
    finally:
        d.close()


@pytest.mark.slow
def test_celery_worker_runs_a_job_through_the_broker(service, tiny_survey):
    """POST /jobs -> CeleryDispatcher -> Redis -> worker process -> PostgreSQL + S3 -> GET /jobs."""
    import redis
    from conftest import upload_survey, wait_for_job

    from workers.celery_app import tasks_key
    from workers.reconcile import RedisLiveness

    c, h = service.client, service.tenant.headers
    pid = upload_survey(c, service.tenant, tiny_survey, service.app.state.storage)
    t0 = time.monotonic()
    r = c.post(f"/projects/{pid}/jobs", json={"options": {"stages": ["aerial_sfm"]}}, headers=h)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    rd = redis.Redis.from_url(service.app.state.settings.broker_url)
    assert len(rd.smembers(tasks_key(job_id))) == 2  # run_stage(aerial_sfm), finalize
    seen = []
    job = wait_for_job(c, h, job_id, 180, seen)
    elapsed = time.monotonic() - t0
    print(f"one-stage job through Celery: {elapsed:.1f} s")
    assert job["status"] == "succeeded", (job, service.worker.text()[-3000:])
    assert [(st["stage"], st["status"]) for st in job["stages"]] == [("aerial_sfm", "succeeded")]
    assert job["stages"][0]["worker"].startswith("midview-test-")
    assert job["metrics"]["aerial_sfm"]["NRI"] == "20/20" and job["progress"] == 1.0
    assert ("running", "aerial_sfm") in {(st, stage) for st, stage, _ in seen}
    with service.app.state.sessionmaker() as s:
        assert s.get(Job, job_id).celery_root_id
    arts = {a["name"]: a for a in c.get(f"/jobs/{job_id}/artifacts", headers=h).json()}
    report = c.get(f"/artifacts/{arts['sfm/report.json']['id']}/download", headers=h)
    assert (
        report.status_code == 200 and json.loads(report.content)["NRI"] == job["metrics"]["aerial_sfm"]["NRI"]
    )
    # every running task unregistered itself; nothing of the job left in the queues
    assert not any(k for k in rd.scan_iter("midview:task:*:alive") if job_id.encode() in (rd.get(k) or b""))
    assert job_id not in RedisLiveness(rd).snapshot()
    # the worker process's log of the stage, kept by the server: the pipeline's own records too
    text = c.get(f"/jobs/{job_id}/log", headers=h).text
    assert text.startswith("== aerial_sfm (attempt 1, succeeded, ") and " INFO midview.sfm" in text, text[
        :2000
    ]
    assert c.get("/jobs/nope/log", headers=h).status_code == 404


@pytest.mark.slow
def test_celery_failure_fails_the_job_and_queues_the_webhook(service, tiny_survey):
    """A stage error that no retry can fix (the project's cameras.json names a camera of another size
    than the images) fails the stage and the job, with the error text, and queues the job.failed webhook
    delivery."""
    import sqlalchemy as sa
    from conftest import upload_survey, wait_for_job

    from shared.db.models import WebhookDelivery

    c, h = service.client, service.tenant.headers
    r = c.post("/webhooks", json={"url": "http://127.0.0.1:9/hook"}, headers=h)
    assert r.status_code == 201, r.text
    pid = upload_survey(c, service.tenant, tiny_survey, service.app.state.storage)
    cam = {"model": "PINHOLE", "width": 640, "height": 480, "params": [500.0, 500.0, 320.0, 240.0]}
    assert (
        c.put(f"/projects/{pid}/cameras", json={"aerial": cam, "ground": cam}, headers=h).status_code == 200
    )
    job_id = c.post(f"/projects/{pid}/jobs", json={"options": {"stages": ["aerial_sfm"]}}, headers=h).json()[
        "id"
    ]
    job = wait_for_job(c, h, job_id, 120)
    assert job["status"] == "failed", job
    assert "aerial_sfm" in job["error"] and "cameras.json" in job["error"], job["error"]
    assert [(st["stage"], st["status"]) for st in job["stages"]] == [("aerial_sfm", "failed")]
    assert "the camera is 640x480" in job["stages"][0]["error"]
    with service.app.state.sessionmaker() as s:
        events = s.scalars(sa.select(WebhookDelivery.event).where(WebhookDelivery.job_id == job_id)).all()
    assert events == ["job.failed"]
    assert "Task midview.run_stage" in service.worker.text()


def test_task_error_policy(monkeypatch):
    """Transient errors are retried with back-off (no failure recorded), others fail the job once and
    propagate, JobStopped ends the task quietly (Ignore)."""
    from celery.exceptions import Ignore

    from workers import execute, tasks

    failed = []
    monkeypatch.setattr(execute, "fail", lambda job_id, stage, e, settings: failed.append((job_id, stage, e)))
    monkeypatch.setattr(tasks, "redis_client", lambda: None)

    class Retried(Exception):
        pass

    class FakeTask:
        name = "midview.run_stage"

        def __init__(self, retries):
            self.request = types.SimpleNamespace(id="t1", retries=retries, hostname="h", args=[])
            self.retry_kw = None

        def retry(self, **kw):
            self.retry_kw = kw
            return Retried()

    def boom(exc):
        def fn(settings):
            raise exc

        return fn

    task = FakeTask(retries=0)
    with pytest.raises(Retried):
        tasks._guarded(task, "J", "reduce", boom(ConnectionResetError("peer")))
    assert 1.0 <= task.retry_kw["countdown"] <= 3.0 and failed == []
    task = FakeTask(retries=99)  # retries exhausted: the transient error fails the job
    with pytest.raises(ConnectionResetError):
        tasks._guarded(task, "J", "reduce", boom(ConnectionResetError("peer")))
    assert [(j, s) for j, s, _ in failed] == [("J", "reduce")]
    with pytest.raises(ValueError):
        tasks._guarded(FakeTask(0), "J", "combined_sfm", boom(ValueError("bad")))
    assert [(j, s) for j, s, _ in failed][-1] == ("J", "combined_sfm")
    with pytest.raises(Ignore):
        tasks._guarded(FakeTask(0), "J", "reduce", boom(execute.JobStopped("cancelled")))
    assert len(failed) == 2
    assert all(0.5 * 2 * 2**n <= execute.backoff_s(n) <= 1.5 * 2 * 2**n for n in range(5))


@pytest.mark.slow
def test_periodic_tasks_run_on_the_worker(service):
    """What celery beat sends: reconcile (nothing stalled here) and the webhook deliveries."""
    from workers.celery_app import DELIVER_WEBHOOKS, RECONCILE, make_app

    app = make_app(service.app.state.settings, name="midview-test-beat", set_as_current=False)
    try:
        actions = app.send_task(RECONCILE).get(timeout=60)
        assert isinstance(actions, list) and not any(a.get("error") for a in actions), actions
        assert isinstance(app.send_task(DELIVER_WEBHOOKS).get(timeout=60), int)
    finally:
        app.close()


def test_worker_command_line():
    from cli.worker import worker_argv

    argv = worker_argv("cpu, reduce", 4, beat=True, hostname="w1@%h")
    assert argv == [
        "worker",
        "-Q",
        "cpu,reduce",
        "-c",
        "4",
        "-P",
        "prefork",
        "-l",
        "INFO",
        "-n",
        "w1@%h",
        "-B",
    ]
    with pytest.raises(ValueError, match="unknown queue"):
        worker_argv("gpu,video")


def _running_task(rd, job_id: str, stage: str, timeout_s: float = 30.0) -> tuple[str, int]:
    """(task id, pid of the pool process) of the job's task running stage, from its Redis heartbeat key."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for key in rd.scan_iter("midview:task:*:alive"):
            info = json.loads(rd.get(key) or "{}")
            if info.get("job") == job_id and stage in info.get("args", []):
                return key.decode().split(":")[2], int(info["pid"])
        time.sleep(0.2)
    raise AssertionError(f"no running {stage} task of job {job_id} in Redis")


def _process_gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    return False


@pytest.mark.slow
def test_celery_cancel_stops_the_job(service, tiny_survey):
    """Cancel while train_splat runs: the running task is terminated (revoke): its pool process is
    killed and replaced, its state is REVOKED, the stage reports no more progress; the chain stops, the
    job stays cancelled, and the worker goes on serving."""
    import redis
    from celery.result import AsyncResult
    from conftest import upload_survey, wait_for_job

    from workers.celery_app import make_app

    c, h = service.client, service.tenant.headers
    rd = redis.Redis.from_url(service.app.state.settings.broker_url)
    pid = upload_survey(c, service.tenant, tiny_survey, service.app.state.storage)
    opts = {
        "stages": ["aerial_sfm", "train_splat", "plan_views"],
        "splat_steps": 1000,
        "splat_max_width": 240,
    }
    job_id = c.post(f"/projects/{pid}/jobs", json={"options": opts}, headers=h).json()["id"]
    deadline = time.monotonic() + 120
    while c.get(f"/jobs/{job_id}", headers=h).json()["current_stage"] != "train_splat":
        assert time.monotonic() < deadline, service.worker.text()[-3000:]
        time.sleep(0.3)
    task_id, task_pid = _running_task(rd, job_id, "train_splat")
    assert task_pid != service.worker.proc.pid and not _process_gone(task_pid, 1.0)  # a live pool process
    progress_line = f"job {job_id}: train_splat"
    while progress_line not in service.worker.text():  # the stage reports progress (the worker logs it)
        assert time.monotonic() < deadline + 60, service.worker.text()[-3000:]
        time.sleep(0.3)
    assert c.post(f"/jobs/{job_id}/cancel", headers=h).json()["status"] == "cancelled"
    # the task was terminated, not left to run to its end
    assert _process_gone(task_pid, 15.0), (
        f"pool process {task_pid} still runs:\n{service.worker.text()[-3000:]}"
    )
    app = make_app(service.app.state.settings, name="midview-test-revoked", set_as_current=False)
    try:
        deadline = time.monotonic() + 15
        while AsyncResult(task_id, app=app).state != "REVOKED":
            assert time.monotonic() < deadline, AsyncResult(task_id, app=app).state
            time.sleep(0.2)
    finally:
        app.close()
    log_after_cancel = len(service.worker.text())
    time.sleep(3.0)
    assert progress_line not in service.worker.text()[log_after_cancel:]  # no more progress
    job = c.get(f"/jobs/{job_id}", headers=h).json()
    assert job["status"] == "cancelled"
    assert [(st["stage"], st["status"]) for st in job["stages"]] == [
        ("aerial_sfm", "succeeded"), ("train_splat", "cancelled")]  # fmt: skip
    # the worker still works (a short job after the terminated one)
    r = c.post(f"/projects/{pid}/jobs", json={"options": {"stages": ["aerial_sfm"]}}, headers=h)
    assert wait_for_job(c, h, r.json()["id"], 120)["status"] == "succeeded", service.worker.text()[-3000:]
    assert service.worker.alive()


# -- a worker node that died ---------------------------------------------------------------------
def _node_name(worker) -> str:
    """The Celery node name of the test worker, as it answers a ping."""
    import socket

    return worker.hostname.replace("%h", socket.gethostname())


def _unacked(rd, job_id: str, stage: str) -> str:
    """A message of the job reserved by a worker, as the Redis transport keeps it until acknowledged:
    what a node that died leaves behind for the visibility timeout (hours)."""
    tag = f"test-{uuid.uuid4().hex}"
    message = {"body": "", "headers": {"task": "midview.run_stage", "argsrepr": f"['{job_id}', '{stage}']"}}
    rd.hset("unacked", tag, json.dumps([message, "", "gpu"]))
    return tag


def _running_job(s, project_id, stage, node, heartbeat_age_s, now):
    """A running job whose stage run was last heard of heartbeat_age_s ago, from node."""
    job = crud.create_job(s, project_id, {"stages": ["aerial_sfm", "train_splat"]})
    crud.set_job_status(s, job, JobStatus.running)
    run = crud.start_stage(s, job, stage, worker=f"{node}:4242")
    run.node, run.heartbeat_at = node, now - timedelta(seconds=heartbeat_age_s)
    run.started_at = now - timedelta(seconds=heartbeat_age_s + 60)
    job.created_at = job.started_at = now - timedelta(seconds=heartbeat_age_s + 120)
    job.celery_root_id = str(uuid.uuid4())
    s.flush()
    return job.id


@pytest.mark.slow
def test_reconciler_redispatches_the_stages_of_a_dead_node(service):
    """A stage whose heartbeat is old and whose node does not answer a Celery ping (the real worker
    answers, a made-up node does not) is given up and dispatched again, although the dead node's message
    still sits in `unacked`; a quiet stage on a live node, or a recent heartbeat, is left alone; a very
    old heartbeat is given up whatever its node says."""
    import redis
    from conftest import RecordingDispatcher

    from workers.celery_app import make_app
    from workers.reconcile import NodeCheck, RedisLiveness, celery_ping, reconcile

    settings, sm = service.app.state.settings, service.app.state.sessionmaker
    live_node, dead_node = _node_name(service.worker), f"gpu-{uuid.uuid4().hex[:6]}@lost-host"
    now = utcnow()
    with sm() as s:
        pid = crud.create_project(s, service.tenant.id, f"dead-node-{uuid.uuid4().hex[:6]}").id
        dead = _running_job(s, pid, "train_splat", dead_node, 600, now)
        quiet = _running_job(s, pid, "train_splat", live_node, 600, now)
        fresh = _running_job(s, pid, "train_splat", dead_node, 5, now)
        hung = _running_job(s, pid, "aerial_sfm", live_node, 7200, now)
        s.commit()
    mine = {dead, quiet, fresh, hung}
    rd = redis.Redis.from_url(settings.broker_url)
    tag = _unacked(rd, dead, "train_splat")
    app = make_app(settings, name="midview-test-ping", set_as_current=False)
    d = RecordingDispatcher()
    try:
        parts = RedisLiveness(rd).parts()
        assert dead in parts.reserved and dead in parts.all()  # the plain probe: "live" for hours
        nodes = NodeCheck(celery_ping(app), 120, 1800, active=parts.running | parts.queued)
        with sm() as s:
            plain = reconcile(s, RecordingDispatcher(), now, 900, is_live=parts.all())
            assert dead not in {a.job_id for a in plain}  # without the node check: left for hours
            s.rollback()
            actions = [
                a for a in reconcile(s, d, now, 900, is_live=parts.all(), nodes=nodes) if a.job_id in mine
            ]
            s.commit()
        assert {(a.job_id, a.from_stage) for a in actions} == {(dead, "train_splat"), (hung, "aerial_sfm")}
        assert dead_node in next(a.reason for a in actions if a.job_id == dead)
        assert sorted(c for c in d.calls if c[1] in mine) == [
            ("submit", j, st) for j, st in sorted([(dead, "train_splat"), (hung, "aerial_sfm")])
        ]
        with sm() as s:
            runs = {
                j: [
                    (r.status.value, r.error)
                    for r in s.scalars(sa.select(StageRun).where(StageRun.job_id == j))
                ]
                for j in mine
            }
        assert (
            runs[dead][0][0] == "failed" and dead_node in runs[dead][0][1] and "abandoned" in runs[dead][0][1]
        )
        assert runs[hung][0][0] == "failed" and runs[quiet] == runs[fresh] == [("running", None)]
        # the next pass leaves them: the given-up runs are closed, the jobs were just dispatched again
        with sm() as s:
            later = now + timedelta(seconds=60)
            assert [a for a in reconcile(s, d, later, 900, nodes=nodes) if a.job_id in mine] == []
    finally:
        rd.hdel("unacked", tag)
        app.close()
        with sm() as s:
            for j in mine:
                crud.set_job_status(s, j, JobStatus.cancelled)
                for run in s.scalars(sa.select(StageRun).where(StageRun.job_id == j)):
                    if run.status == StageStatus.running:
                        crud.finish_stage(s, run, StageStatus.cancelled)
            s.commit()


@pytest.mark.slow
def test_a_job_whose_worker_node_died_completes(service, tiny_survey):
    """The job's stage was running on a node that died (old heartbeat, no answer to a ping, its message
    left in `unacked`): the periodic reconcile task on the real worker dispatches it again, and the job
    completes there."""
    import redis
    from conftest import upload_survey, wait_for_job

    from workers.celery_app import RECONCILE, make_app

    c, h = service.client, service.tenant.headers
    settings, sm = service.app.state.settings, service.app.state.sessionmaker
    pid = upload_survey(c, service.tenant, tiny_survey, service.app.state.storage)
    dead_node = f"gpu-{uuid.uuid4().hex[:6]}@lost-host"
    with sm() as s:
        job_id = _running_job(s, pid, "aerial_sfm", dead_node, 600, utcnow())
        s.get(Job, job_id).options = {"stages": ["aerial_sfm"]}
        s.commit()
    rd = redis.Redis.from_url(settings.broker_url)
    tag = _unacked(rd, job_id, "aerial_sfm")
    app = make_app(settings, name="midview-test-beat", set_as_current=False)
    try:
        actions = [a for a in app.send_task(RECONCILE).get(timeout=60) if a["job_id"] == job_id]
    finally:
        rd.hdel("unacked", tag)
        app.close()
    assert len(actions) == 1 and actions[0]["from_stage"] == "aerial_sfm" and not actions[0]["error"], actions
    job = wait_for_job(c, h, job_id, 180)
    assert job["status"] == "succeeded", (job, service.worker.text()[-3000:])
    live_node = _node_name(service.worker)
    assert [(st["stage"], st["status"], st["node"]) for st in job["stages"]] == [
        ("aerial_sfm", "failed", dead_node),
        ("aerial_sfm", "succeeded", live_node),
    ]
    assert job["stages"][1]["heartbeat_at"] is not None
