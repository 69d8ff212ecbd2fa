"""Migrations, models and CRUD on SQLite (a tmp file) and PostgreSQL (a throwaway database)."""

from __future__ import annotations

import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from servers import PostgresServer
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.pos import PosRecord, ypr_to_matrix
from shared.db import crud
from shared.db.models import (
    ApiKey,
    Artifact,
    Base,
    Image,
    Job,
    JobStatus,
    PosRecordRow,
    Project,
    StageRun,
    StageStatus,
)
from shared.db.session import (
    current_revision,
    downgrade_database,
    make_engine,
    make_sessionmaker,
    session_scope,
    upgrade_database,
)

REPO = Path(__file__).resolve().parents[1]
HEAD = "0008"
TABLES = {
    "tenants",
    "api_keys",
    "projects",
    "campaigns",
    "images",
    "pos_records",
    "jobs",
    "stage_runs",
    "artifacts",
    "webhooks",
    "webhook_deliveries",
    "uploads",
}
SHA_A, SHA_B = "a" * 64, "b" * 64


def _new_url(backend: str, tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> str:
    if backend == "sqlite":
        return f"sqlite:///{tmp_path_factory.mktemp('db') / 'midview.db'}"
    server: PostgresServer = request.getfixturevalue("postgres_server")
    return server.create_database()


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def engine(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[sa.Engine]:
    """A migrated database of each backend, shared by the module (tests roll back)."""
    url = _new_url(request.param, tmp_path_factory, request)
    upgrade_database(url)
    eng = make_engine(url)
    yield eng
    eng.dispose()


@pytest.fixture
def session(engine: sa.Engine) -> Iterator[Session]:
    """A session whose work is rolled back at the end of the test."""
    s = make_sessionmaker(engine)()
    try:
        yield s
    finally:
        s.rollback()
        s.close()


def _name(what: str) -> str:
    return f"{what}-{uuid.uuid4().hex[:8]}"


def _project(session: Session) -> Project:
    tenant = crud.create_tenant(session, _name("tenant"))
    return crud.create_project(session, tenant.id, "survey", origin=(55.7, 13.19, 70.0))


def _table_names(url: str) -> set[str]:
    eng = make_engine(url, poolclass=sa.pool.NullPool)
    try:
        return set(sa.inspect(eng).get_table_names())
    finally:
        eng.dispose()


# migrations
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_migrations_upgrade_and_downgrade(
    backend: str, tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> None:
    url = _new_url(backend, tmp_path_factory, request)
    assert current_revision(url) is None
    upgrade_database(url)
    assert current_revision(url) == HEAD
    assert TABLES <= _table_names(url)
    upgrade_database(url)  # idempotent

    # the schema the migrations build is the one the models describe
    eng = make_engine(url, poolclass=sa.pool.NullPool)
    with eng.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
    eng.dispose()

    downgrade_database(url)
    assert current_revision(url) is None
    assert not TABLES & _table_names(url)

    # the alembic command line (alembic.ini at the repository root) does the same
    for args in (["upgrade", "head"], ["downgrade", "base"]):
        cmd = [sys.executable, "-m", "alembic", "-x", f"url={url}", *args]
        r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
    assert current_revision(url) is None


def test_session_scope_commits_or_rolls_back(engine: sa.Engine) -> None:
    name = _name("scoped")
    with session_scope(engine) as s:
        tenant = crud.create_tenant(s, name)
    with pytest.raises(RuntimeError), session_scope(engine) as s:
        crud.create_project(s, tenant.id, "never")
        raise RuntimeError("boom")
    with session_scope(engine) as s:
        assert crud.get_tenant(s, tenant.id).name == name
        assert crud.list_projects(s, tenant.id) == []
        s.delete(crud.get_tenant(s, tenant.id))


# tenants, API keys, isolation
def test_api_keys_are_hashed_and_revocable(session: Session) -> None:
    tenant = crud.create_tenant(session, _name("acme"))
    key, plaintext = crud.create_api_key(session, tenant.id, "ci", pepper="")
    assert plaintext.startswith("mv_") and len(plaintext) > 40
    assert key.prefix == plaintext[:11]
    stored = session.execute(sa.select(ApiKey.__table__)).all()
    assert not any(plaintext in str(value) for row in stored for value in row)  # never stored in clear
    assert key.key_hash == crud.hash_api_key(plaintext, pepper="")
    assert crud.get_tenant_by_api_key(session, plaintext, pepper="") is tenant
    assert crud.get_tenant_by_api_key(session, plaintext + "x", pepper="") is None
    assert crud.get_tenant_by_api_key(session, "", pepper="") is None
    assert crud.get_tenant_by_api_key(session, plaintext, pepper="other secret") is None
    assert [k.id for k in crud.list_api_keys(session, tenant.id)] == [key.id]

    crud.revoke_api_key(session, key.id, tenant_id=tenant.id)
    assert key.revoked_at is not None
    assert crud.get_tenant_by_api_key(session, plaintext, pepper="") is None


def test_api_key_with_pepper(session: Session) -> None:
    tenant = crud.create_tenant(session, _name("peppered"))
    key, plaintext = crud.create_api_key(session, tenant.id, pepper="s3cret")
    assert key.key_hash != crud.hash_api_key(plaintext, pepper="")
    assert crud.get_tenant_by_api_key(session, plaintext, pepper="s3cret") is tenant


def test_tenant_isolation(session: Session) -> None:
    a = crud.create_tenant(session, _name("a"))
    b = crud.create_tenant(session, _name("b"))
    pa = crud.create_project(session, a.id, "shared-name")
    pb = crud.create_project(session, b.id, "shared-name")  # names are unique per tenant only
    job = crud.create_job(session, pa.id)
    key, _ = crud.create_api_key(session, a.id)
    assert crud.get_project(session, pa.id, tenant_id=a.id) is pa
    assert crud.get_project(session, pa.id, tenant_id=b.id) is None
    assert crud.get_project(session, "not-a-uuid", tenant_id=a.id) is None
    assert [p.id for p in crud.list_projects(session, b.id)] == [pb.id]
    assert crud.get_job(session, job.id, tenant_id=a.id) is job
    assert crud.get_job(session, job.id, tenant_id=b.id) is None
    with pytest.raises(crud.NotFoundError):
        crud.revoke_api_key(session, key.id, tenant_id=b.id)


def test_unique_names(session: Session) -> None:
    name = _name("t")
    tenant = crud.create_tenant(session, name)
    with pytest.raises(crud.ConflictError):
        crud.create_tenant(session, name)
    crud.create_project(session, tenant.id, "p")
    with pytest.raises(crud.ConflictError):
        crud.create_project(session, tenant.id, "p")
    with pytest.raises(crud.NotFoundError):
        crud.create_project(session, str(uuid.uuid4()), "p")
    # the database enforces it too, even without the helper's check
    session.add(Project(tenant_id=tenant.id, name="p"))
    with pytest.raises(IntegrityError):
        session.flush()


# images and POS
def test_add_image_idempotent_and_conflicts(session: Session) -> None:
    project = _project(session)
    kw = dict(sha256=SHA_A, size_bytes=1234, storage_key="k/aerial/A0001.jpg", width=1600, height=1200)
    img, created = crud.add_image(session, project.id, "aerial/A0001.jpg", **kw)
    assert created and img.image_set == "aerial" and img.width == 1600
    again, created = crud.add_image(session, project.id, "aerial/A0001.jpg", **kw)
    assert not created and again.id == img.id
    with pytest.raises(crud.ConflictError):
        crud.add_image(session, project.id, "aerial/A0001.jpg", **{**kw, "sha256": SHA_B})

    other = crud.create_project(session, project.tenant_id, "other")
    _, created = crud.add_image(session, other.id, "aerial/A0001.jpg", **{**kw, "sha256": SHA_B})
    assert created  # the same name in another project is another image
    crud.add_image(session, project.id, "ground/G0001.jpg", **{**kw, "metadata": {"exif": {"iso": 100}}})
    assert [i.name for i in crud.list_images(session, project.id)] == ["aerial/A0001.jpg", "ground/G0001.jpg"]
    assert [i.name for i in crud.list_images(session, project.id, "ground")] == ["ground/G0001.jpg"]
    assert crud.get_image(session, project.id, "ground/G0001.jpg").meta == {"exif": {"iso": 100}}

    for bad in ("oblique/x.jpg", "A0001.jpg", "aerial/../x.jpg", "aerial/a/b.jpg", "/aerial/x.jpg"):
        with pytest.raises(ValueError):
            crud.add_image(session, project.id, bad, **kw)
    with pytest.raises(ValueError):
        crud.add_image(session, project.id, "aerial/A0002.jpg", **{**kw, "sha256": "xyz"})


def test_image_set_check_constraint(session: Session) -> None:
    project = _project(session)
    session.add(
        Image(
            project_id=project.id, name="x/1.jpg", image_set="x", sha256=SHA_A, size_bytes=1, storage_key="k"
        )
    )
    with pytest.raises(IntegrityError):
        session.flush()


def test_pos_records_upsert(session: Session) -> None:
    project = _project(session)
    R = ypr_to_matrix(90, -45, 0)
    records = [
        PosRecord("aerial/A0001.jpg", 55.7047, 13.1910, 130.5, R, 0.5, 1.0, 1.5),
        {"name": "ground/G0001.jpg", "lat": 55.7049, "lon": 13.1913, "h": 71.8},
    ]
    assert crud.add_pos_records(session, project.id, records, source_format="midview-pos-v1") == 2
    rows = crud.list_pos_records(session, project.id)
    assert [r.image_name for r in rows] == ["aerial/A0001.jpg", "ground/G0001.jpg"]
    np.testing.assert_allclose(np.array(rows[0].attitude), R)
    assert rows[1].attitude is None and rows[1].std_xy is None

    crud.add_pos_records(
        session, project.id, [{"name": "ground/G0001.jpg", "lat": 1.0, "lon": 2.0, "h": 3.0}]
    )
    rows = crud.list_pos_records(session, project.id)
    assert len(rows) == 2 and (rows[1].lat, rows[1].lon, rows[1].h) == (1.0, 2.0, 3.0)
    with pytest.raises(ValueError):
        crud.add_pos_records(
            session, project.id, [{"name": "a/x.jpg", "lat": float("nan"), "lon": 0, "h": 0}]
        )


# jobs
def test_job_lifecycle(session: Session) -> None:
    project = _project(session)
    job = crud.create_job(session, project.id, options={"method": "midview", "views": 8})
    assert job.status == JobStatus.queued and job.progress == 0 and job.attempt == 1
    assert job.options == {"method": "midview", "views": 8}

    crud.update_job_results(session, job, celery_root_id="celery-123")
    run = crud.start_stage(session, job.id, "features", worker="w1@host")
    assert job.status == JobStatus.running and job.started_at is not None
    assert job.current_stage == "features" and run.attempt == 1
    crud.update_job_progress(session, job, 0.25)
    crud.finish_stage(session, run, output_key="k/features.h5")
    assert run.status == StageStatus.succeeded and run.duration_s >= 0
    assert set(job.timings) == {"features"}
    with pytest.raises(crud.InvalidTransitionError):
        crud.finish_stage(session, run)  # already finished

    retry = crud.start_stage(session, job, "match")
    crud.finish_stage(session, retry, StageStatus.failed, error="CUDA OOM")
    retry = crud.start_stage(session, job, "match")
    assert retry.attempt == 2
    crud.finish_stage(session, retry)
    art = crud.record_artifact(session, job, "matches", "matches.h5", "k/m.h5", size_bytes=10, sha256=SHA_A)
    art2 = crud.record_artifact(session, job, "matches", "matches.h5", "k/m2.h5", size_bytes=20)
    assert art2.id == art.id and art.storage_key == "k/m2.h5"
    crud.update_job_results(session, job, metrics={"ncm": 120})

    crud.set_job_status(session, job, "succeeded")
    assert job.progress == 1.0 and job.finished_at >= job.started_at
    assert [a.name for a in crud.list_artifacts(session, job.id)] == ["matches.h5"]
    assert job.metrics == {"ncm": 120} and job.celery_root_id == "celery-123"
    with pytest.raises(crud.InvalidTransitionError):
        crud.set_job_status(session, job, JobStatus.running)  # succeeded -> running needs a rerun
    with pytest.raises(crud.InvalidTransitionError):
        crud.update_job_progress(session, job, 0.5)
    with pytest.raises(crud.InvalidTransitionError):
        crud.start_stage(session, job, "features")

    crud.rerun_job(session, job)
    assert job.status == JobStatus.queued and job.attempt == 2
    assert job.progress == 0 and job.finished_at is None and job.error is None and job.metrics == {}
    assert [(r.stage, r.attempt) for r in job.stage_runs] == [("features", 1), ("match", 1), ("match", 2)]

    # reload from the database: timestamps come back timezone-aware, JSON intact
    session.expire_all()
    again = crud.get_job(session, job.id)
    assert again.created_at.tzinfo is not None and again.options["views"] == 8
    assert session.get(StageRun, run.id).started_at.utcoffset().total_seconds() == 0


def test_stage_logs_are_appended_and_read_apart_from_the_status(session: Session) -> None:
    """Each stage run keeps the lines appended to it (in one statement each: fan-out units append from
    several processes); the status read leaves them out; a rerun clears the progress message."""
    job = crud.create_job(session, _project(session).id, options={})
    first = crud.start_stage(session, job, "aerial_sfm")
    crud.update_job_progress(session, job, 0.1, "aerial_sfm", "registering 12/20" + "x" * 900)
    assert job.progress_message.startswith("registering 12/20") and len(job.progress_message) == 500
    crud.append_stage_log(session, first.id, "10:00:00 aerial_sfm   0%\n")
    crud.append_stage_log(session, first.id, "10:00:05 INFO midview.sfm: 20 of 20 registered\n")
    crud.finish_stage(session, first)
    crud.start_stage(session, job, "train_splat")
    session.commit()
    session.expire_all()
    logs = crud.stage_logs(session, job.id)
    assert [(r.stage, text) for r, text in logs] == [
        ("aerial_sfm", "10:00:00 aerial_sfm   0%\n10:00:05 INFO midview.sfm: 20 of 20 registered\n"),
        ("train_splat", ""),
    ]
    _, row, runs = crud.job_status_rows(session, job.id)
    assert row.progress_message.startswith("registering") and all("log" not in r._fields for r in runs)
    crud.set_job_status(session, job, JobStatus.failed, error="x")
    crud.rerun_job(session, job)
    assert job.progress_message is None


@pytest.mark.parametrize(
    ("path", "bad"),
    [
        ([], "succeeded"),  # queued -> succeeded skips running
        (["running", "succeeded"], "running"),
        (["running", "succeeded"], "failed"),
        (["running", "failed"], "succeeded"),
        (["cancelled"], "running"),
        (["running", "cancelled"], "queued"),
        (["running"], "queued"),
    ],
)
def test_invalid_job_transitions(session: Session, path: list[str], bad: str) -> None:
    job = crud.create_job(session, _project(session).id)
    for status in path:
        crud.set_job_status(session, job.id, status)
    before = job.status
    with pytest.raises(crud.InvalidTransitionError):
        crud.set_job_status(session, job.id, bad)
    assert job.status == before
    crud.set_job_status(session, job, before)  # the same status again is a no-op


def test_job_failure_and_progress_bounds(session: Session) -> None:
    job = crud.create_job(session, _project(session).id)
    with pytest.raises(ValueError):
        crud.update_job_progress(session, job, 1.5)
    crud.update_job_progress(session, job, 0.1, stage="features")  # a queued job starts running
    assert job.status == JobStatus.running and job.current_stage == "features"
    crud.set_job_status(session, job, JobStatus.failed, error="Traceback ...")
    assert job.error == "Traceback ..." and job.finished_at is not None
    with pytest.raises(crud.InvalidTransitionError):
        crud.rerun_job(session, crud.create_job(session, job.project_id))  # not finished yet
    with pytest.raises(crud.NotFoundError):
        crud.set_job_status(session, str(uuid.uuid4()), "running")
    job.progress = 2.0  # the check constraint backs the helper
    with pytest.raises(IntegrityError):
        session.flush()


# cascades
def _count(session: Session, model: type[Base], **where: str) -> int:
    stmt = sa.select(sa.func.count()).select_from(model)
    for col, value in where.items():
        stmt = stmt.where(getattr(model, col) == value)
    return session.scalar(stmt)


def test_deleting_a_project_removes_its_children(session: Session) -> None:
    project = _project(session)
    keep = crud.create_project(session, project.tenant_id, "keep")
    for p in (project, keep):
        crud.add_image(session, p.id, "aerial/A1.jpg", sha256=SHA_A, size_bytes=1, storage_key="k")
        crud.add_pos_records(session, p.id, [{"name": "aerial/A1.jpg", "lat": 1, "lon": 2, "h": 3}])
        job = crud.create_job(session, p.id)
        crud.finish_stage(session, crud.start_stage(session, job, "features"))
        crud.record_artifact(session, job, "report", "report.json", "k/r.json")
    job_id = crud.list_jobs(session, project.id)[0].id

    crud.delete_project(session, project)
    session.expire_all()
    assert _count(session, Image, project_id=project.id) == 0
    assert _count(session, PosRecordRow, project_id=project.id) == 0
    assert _count(session, Job, project_id=project.id) == 0
    assert _count(session, StageRun, job_id=job_id) == 0
    assert _count(session, Artifact, job_id=job_id) == 0
    assert _count(session, Image, project_id=keep.id) == 1
    assert _count(session, StageRun) >= 1

    # ON DELETE CASCADE in the database itself, without the ORM
    session.execute(sa.text("DELETE FROM tenants WHERE id = :id"), {"id": keep.tenant_id})
    assert _count(session, Project, tenant_id=keep.tenant_id) == 0
    assert _count(session, Image, project_id=keep.id) == 0


def test_a_write_after_a_stale_read_waits_for_the_lock(engine: sa.Engine) -> None:
    """The API reads a job, the worker commits progress, the API cancels the job (the embedded service
    on SQLite: a deferred transaction that has read could not take the write lock and failed with
    "database is locked" at once). The cancel is written, and so is the worker's progress."""
    make = make_sessionmaker(engine)
    with make() as s:
        job_id = crud.create_job(s, _project(s).id).id
        crud.set_job_status(s, job_id, JobStatus.running)
        s.commit()
    with make() as api, make() as worker:
        assert api.get(Job, job_id).status == JobStatus.running  # the API's transaction has read
        crud.update_job_progress(worker, worker.get(Job, job_id), 0.5)
        worker.commit()  # ... and the worker has committed since
        crud.set_job_status(api, job_id, JobStatus.cancelled)
        api.commit()
    with make() as s:
        job = s.get(Job, job_id)
        assert job.status == JobStatus.cancelled and job.progress == 0.5
        # a transaction that has written already is not committed early: its work rolls back as one
        crud.update_job_results(s, job, metrics={"ncm": 1})
        s.flush()
        crud.rerun_job(s, job_id)
        s.rollback()
        job = s.get(Job, job_id)
        assert job.status == JobStatus.cancelled and job.metrics != {"ncm": 1}
