"""The one code path that runs pipeline work for the service: Celery tasks (workers/tasks.py) and the
embedded dispatcher (workers/embedded.py) both call these functions.

Each unit of work opens short database sessions to report (stage runs, progress, artifacts, status),
brings the job folder on this machine up to date with storage (jobsync.materialize + pull), runs
services.pipeline, and pushes what it produced:

- execute_stage(job_id, stage): one pipeline stage;
- prepare_fan_out(job_id, stage): the start of a fan-out stage (services.pipeline.FanOut: the blocks'
  plan of train_blocks, the feature cache of match_views, once), returns the unit names and their queue;
- execute_unit(job_id, stage, unit): one unit of the fan-out (blocks/B/, matches/VIEW.h5);
- execute_stage(job_id, stage) after the fan-out: checks every unit is done (those done are skipped),
  summarises them, writes the stage marker;
- finalize(job_id): the job succeeded (metrics from the stage markers) + webhook event;
- fail(job_id, stage, error): the stage run and the job failed + webhook event.

A job that was cancelled (or finished) meanwhile raises JobStopped: at the start of every unit and at
every progress report (crud.update_job_progress refuses to update a finished job).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import random
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import sqlalchemy as sa
from sqlalchemy.orm import Session

from services.pipeline import STAGES, JobOptions, set_threads
from shared.config import Settings
from shared.db import crud
from shared.db.models import TERMINAL_JOB_STATUSES, Job, JobStatus, StageRun, StageStatus, utcnow
from shared.db.session import get_engine, session_scope
from shared.outcome import job_outcome
from shared.storage import Storage, StorageKeyError, get_storage
from workers import jobsync
from workers.stagelog import StageLog, captured

if TYPE_CHECKING:
    from services.pipeline import FanOut
    from services.pipeline import Job as PipelineJob

log = logging.getLogger("midview.workers")

MAX_ERROR_CHARS = 4000


class JobStopped(Exception):
    """The job was cancelled, finished or deleted meanwhile: stop without recording a failure."""


# -- errors worth a retry ------------------------------------------------------------------------
_PERMANENT_OS_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError)


def _transient_types() -> tuple[type[BaseException], ...]:
    types: list[type[BaseException]] = []
    try:
        import sqlalchemy.exc as sx

        types += [sx.OperationalError, sx.DisconnectionError, sx.TimeoutError]
    except ImportError:  # pragma: no cover
        pass
    try:
        import botocore.exceptions as bx

        types += [bx.ConnectionError, bx.HTTPClientError]  # endpoint unreachable, read timeouts, ...
    except ImportError:  # pragma: no cover
        pass
    try:
        import redis.exceptions as rx

        types += [rx.ConnectionError, rx.TimeoutError, rx.BusyLoadingError]
    except ImportError:  # pragma: no cover
        pass
    try:
        import kombu.exceptions as kx

        types += [kx.OperationalError]
    except ImportError:  # pragma: no cover
        pass
    return tuple(types)


_TRANSIENT = _transient_types()
_TRANSIENT_S3_CODES = {"SlowDown", "RequestTimeout", "InternalError", "ServiceUnavailable", "Throttling"}


def is_transient(exc: BaseException) -> bool:
    """Whether exc (or what caused it) is a connection or availability problem that a retry may fix:
    OSError other than a missing/forbidden file, database/S3/Redis/broker connection errors, S3 5xx."""
    seen = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, JobStopped):
            return False
        if isinstance(e, OSError) and not isinstance(e, _PERMANENT_OS_ERRORS):
            return True
        if _TRANSIENT and isinstance(e, _TRANSIENT):
            return True
        resp = getattr(e, "response", None)
        if isinstance(resp, dict):  # botocore ClientError
            err, meta = resp.get("Error", {}), resp.get("ResponseMetadata", {})
            if err.get("Code") in _TRANSIENT_S3_CODES or int(meta.get("HTTPStatusCode") or 0) >= 500:
                return True
        e = e.__cause__ or e.__context__
    return False


BACKOFF_BASE_S = 2.0
BACKOFF_MAX_S = 300.0


def backoff_s(retries: int) -> float:
    """Delay before retry number retries + 1: exponential, capped, with jitter (x0.5 to x1.5)."""
    return min(BACKOFF_MAX_S, BACKOFF_BASE_S * 2**retries) * random.uniform(0.5, 1.5)


def error_text(stage: str | None, exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}"
    if stage:
        text = f"stage {stage}: {text}"
    return text[:MAX_ERROR_CHARS]


# -- context -------------------------------------------------------------------------------------
@dataclass
class Context:
    settings: Settings
    engine: sa.Engine
    storage: Storage
    work_dir: Path

    @contextmanager
    def session(self) -> Iterator[Session]:
        with session_scope(self.engine) as s:
            yield s


_storages: dict[tuple, Storage] = {}
_lock = threading.Lock()


def get_context(settings: Settings) -> Context:
    """Engine (process-wide per URL), storage (cached per configuration) and work folder."""
    key = (
        settings.storage,
        str(settings.storage_root),
        settings.s3_endpoint_url,
        settings.s3_bucket,
        settings.s3_access_key,
        os.getpid(),  # boto3 clients must not cross a fork
    )
    with _lock:
        storage = _storages.get(key)
        if storage is None:
            storage = _storages[key] = get_storage(settings)
    work_dir = Path(settings.work_dir or Path(settings.data_dir) / "work")
    return Context(settings, get_engine(settings.database_url), storage, work_dir)


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclass
class JobInfo:
    """What a unit needs of the job row after its session is closed."""

    id: str
    prefix: str  # the job's storage prefix (tenants/T/projects/P/jobs/J/)
    stages: list[str]
    run_id: str | None = None
    log_run_id: str | None = None  # the stage run a fan-out unit's log goes to (its stage's running run)
    forced: bool = False  # run the stage even where it is up to date (a forced rerun)

    @property
    def log_run(self) -> str | None:
        """The stage run this unit of work's log goes to."""
        return self.run_id or self.log_run_id


def _info(row: Job) -> JobInfo:
    options = JobOptions.model_validate(row.options or {})
    return JobInfo(row.id, jobsync.job_storage_prefix(row), list(options.stages))


def _forced(session: Session, row: Job, stage: str) -> bool:
    """Whether this attempt runs `stage` even where it is up to date: a forced rerun from it or an earlier
    stage (Job.force_from), and no run of it in this attempt has succeeded yet (a task delivered again
    after its stage succeeded skips it)."""
    if row.force_from is None or row.force_from not in STAGES or stage not in STAGES:
        return False
    if list(STAGES).index(stage) < list(STAGES).index(row.force_from):
        return False
    done = session.scalar(
        sa.select(sa.func.count())
        .select_from(StageRun)
        .where(
            StageRun.job_id == row.id,
            StageRun.attempt == row.attempt,
            StageRun.stage == stage,
            StageRun.status == StageStatus.succeeded,
        )
    )
    return not done


def _live_row(session: Session, job_id: str) -> Job:
    row = crud.get_job(session, job_id)
    if row is None:
        raise JobStopped(f"job {job_id} no longer exists")
    if row.status in TERMINAL_JOB_STATUSES:
        raise JobStopped(f"job {job_id} is {row.status.value}")
    return row


def _open_run(
    session: Session, row: Job, stage: str, worker: str | None, node: str | None = None
) -> StageRun:
    """The stage run of this attempt: the running one started by the match_views fan-out (or by a
    worker that was lost) is reused; runs of earlier attempts left running are closed. It records the
    worker, its Celery node and a first heartbeat."""
    open_runs = list(
        session.scalars(
            sa.select(StageRun)
            .where(StageRun.job_id == row.id, StageRun.stage == stage, StageRun.status == StageStatus.running)
            .order_by(StageRun.started_at.desc())
        )
    )
    current = None
    for run in open_runs:
        if current is None and row.started_at is not None and run.started_at >= row.started_at:
            current = run
        else:
            crud.finish_stage(session, run, StageStatus.failed, error="abandoned (its worker was lost)")
    if current is not None:
        current.worker = worker or current.worker
        crud.update_job_progress(session, row, row.progress, stage)
    else:
        current = crud.start_stage(session, row, stage, worker=worker)
    current.node = node or current.node
    current.heartbeat_at = utcnow()
    session.flush()
    return current


def heartbeat(job_id: str, stage: str, *, settings: Settings) -> int:
    """Refresh the heartbeat of the job's running runs of stage (called periodically while a task works
    on it); returns how many rows it touched."""
    with get_context(settings).session() as s:
        r = s.execute(
            sa.update(StageRun)
            .where(StageRun.job_id == job_id, StageRun.stage == stage, StageRun.status == StageStatus.running)
            .values(heartbeat_at=utcnow())
        )
        return int(getattr(r, "rowcount", 0) or 0)  # an UPDATE's CursorResult


def _begin(
    ctx: Context, job_id: str, stage: str, worker: str | None, open_run: bool = True, node: str | None = None
) -> JobInfo:
    with ctx.session() as s:
        row = _live_row(s, job_id)
        info = _info(row)
        info.forced = _forced(s, row, stage)
        if open_run:
            info.run_id = _open_run(s, row, stage, worker or worker_name(), node).id
        else:
            info.log_run_id = s.scalar(
                sa.select(StageRun.id)
                .where(
                    StageRun.job_id == job_id, StageRun.stage == stage, StageRun.status == StageStatus.running
                )
                .order_by(StageRun.started_at.desc())
                .limit(1)
            )
    return info


def _keep_log(ctx: Context, info: JobInfo) -> Callable[[StageLog], None]:
    """Writes what a stage log collected to the run's log, in a session of its own."""

    def flush(stage_log: StageLog) -> None:
        with ctx.session() as s:
            stage_log.write(s, info.log_run)

    return flush


def _close_run(ctx: Context, run_id: str | None, status: StageStatus, error: str | None = None) -> None:
    """Close a stage run (best effort: the database may be what failed)."""
    if run_id is None:
        return
    try:
        with ctx.session() as s:
            run = s.get(StageRun, run_id)
            if run is not None and run.status == StageStatus.running:
                crud.finish_stage(s, run, status, error=error)
    except Exception:
        log.exception("could not close stage run %s", run_id)


# -- progress ------------------------------------------------------------------------------------
class ProgressReporter:
    """progress(stage, fraction, message) of services.pipeline -> crud.update_job_progress, with the
    job's overall progress = (index of stage + fraction) / number of stages; at most one write per
    min_interval_s (besides a stage's first and last report). JobStopped when the job was cancelled."""

    def __init__(
        self, ctx: Context, info: JobInfo, min_interval_s: float = 1.0, stage_log: StageLog | None = None
    ):
        self.ctx, self.info, self.min_interval_s = ctx, info, min_interval_s
        self.stage_log = stage_log  # what the stage logged goes to its run with each write
        self._last = -math.inf
        self._last_stage: str | None = None

    def overall(self, stage: str, fraction: float) -> float:
        stages = self.info.stages
        i = stages.index(stage) if stage in stages else 0
        return min(1.0, max(0.0, (i + min(max(fraction, 0.0), 1.0)) / max(len(stages), 1)))

    def __call__(self, stage: str, fraction: float, message: str = "") -> None:
        now = time.monotonic()
        first = stage != self._last_stage
        if not first and fraction < 1.0 and now - self._last < self.min_interval_s:
            return
        self._last, self._last_stage = now, stage
        line = f"{stage} {100 * fraction:3.0f}% {message}".rstrip()
        log.info("job %s: %s", self.info.id, line, extra={"progress_report": True})
        if self.stage_log is not None:
            self.stage_log.add(line, stamp=True)
        try:
            with self.ctx.session() as s:
                crud.update_job_progress(s, self.info.id, self.overall(stage, fraction), stage, message)
                if self.stage_log is not None:
                    self.stage_log.write(s, self.info.log_run)
                if self.info.run_id is not None:  # a progress report is a heartbeat too
                    s.execute(
                        sa.update(StageRun)
                        .where(StageRun.id == self.info.run_id)
                        .values(heartbeat_at=utcnow())
                    )
        except crud.InvalidTransitionError as e:
            raise JobStopped(str(e)) from None
        except crud.NotFoundError as e:
            raise JobStopped(str(e)) from None


# -- job folder ----------------------------------------------------------------------------------
def _materialize(ctx: Context, info: JobInfo) -> PipelineJob:
    """materialize + pull under the job folder's lock; returns the services.pipeline.Job."""
    root = jobsync.job_root(ctx.work_dir, info.id)
    with jobsync.locked(root):
        with ctx.session() as s:
            row = crud.get_job(s, info.id)
            if row is None:
                raise JobStopped(f"job {info.id} no longer exists")
            settings = jobsync.pipeline_settings(ctx.settings)
            job = jobsync.materialize(s, ctx.storage, row, ctx.work_dir, settings)
        stats = jobsync.pull(ctx.storage, info.prefix, root)
    if stats.transferred or stats.deleted:
        log.info("job %s: pulled %s", info.id, stats)
    return job


def _push(
    ctx: Context, info: JobInfo, job: PipelineJob, paths: list, unit: str, mirror: list | None = None
) -> None:
    with jobsync.locked(job.root):
        stats = jobsync.push(ctx.storage, info.prefix, job.root, paths, unit, mirror or [])
    log.info("job %s: pushed %s: %s", info.id, unit, stats)


def _push_stage(ctx: Context, info: JobInfo, job: PipelineJob, stage: str) -> None:
    from services import pipeline

    sd = pipeline.REGISTRY[stage]  # its folders are mirrored (objects of files gone locally deleted)
    owned = list(sd.dirs)
    paths = [*owned, *sd.extra, *sd.outputs(job)]
    paths.append(pipeline.marker_path(job, stage))
    mirror = [d for d in owned if (job.root / d).is_dir()]
    _push(ctx, info, job, paths, stage, mirror)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def artifact_files(root: Path, stage: str) -> list[tuple[str, str, Path]]:
    """(name relative to the job folder, kind, path) of the artifacts a finished stage left in `root`."""
    from services import pipeline

    out = []
    sd = pipeline.REGISTRY.get(stage)
    for pattern, kind in sd.artifacts if sd is not None else ():
        if "*" in pattern:  # folder/* or folder/*.png: the files of one folder
            files = sorted(p for p in root.glob(pattern) if p.is_file())
        else:
            files = [root / pattern] if (root / pattern).is_file() else []
        out += [(p.relative_to(root).as_posix(), kind, p) for p in files]
    return out


def _record_artifacts(session: Session, info: JobInfo, job: PipelineJob, stage: str) -> int:
    files = artifact_files(job.root, stage)
    for rel, kind, p in files:
        crud.record_artifact(
            session,
            info.id,
            kind,
            rel,
            jobsync.files_key(info.prefix, rel),
            size_bytes=p.stat().st_size,
            sha256=_sha256(p),
            content_type=jobsync.content_type(p),
        )
    return len(files)


# -- units ---------------------------------------------------------------------------------------
def execute_stage(
    job_id: str, stage: str, *, settings: Settings, worker: str | None = None, node: str | None = None
) -> dict:
    """Run one stage of a job (skipped when up to date); returns {stage, skipped, seconds, summary}.
    node: the Celery node name, recorded on the stage run for the reconciler's liveness check."""

    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; stages are {list(STAGES)}")
    ctx = get_context(settings)
    info = _begin(ctx, job_id, stage, worker, node=node)
    with captured(_keep_log(ctx, info)) as stage_log:
        return _execute_stage(ctx, info, job_id, stage, stage_log)


def _execute_stage(ctx: Context, info: JobInfo, job_id: str, stage: str, stage_log: StageLog) -> dict:
    from services import pipeline

    try:
        job = _materialize(ctx, info)
        report = ProgressReporter(ctx, info, stage_log=stage_log)
        # after the fan-out, match_views finds every view up to date and only writes its marker
        marker = pipeline.run_stage(job, stage, progress=report, force=info.forced)
        _push_stage(ctx, info, job, stage)
        with ctx.session() as s:
            _live_row(s, job_id)
            n = _record_artifacts(s, info, job, stage)
            run = s.get(StageRun, info.run_id)
            status = StageStatus.skipped if marker.get("skipped") else StageStatus.succeeded
            output_key = jobsync.files_key(info.prefix, f"{stage_dir(stage)}/")
            if run is not None and run.status == StageStatus.running:
                crud.finish_stage(s, run, status, output_key=output_key)
            else:  # the reconciler gave this run up (its node looked dead) and dispatched it again
                log.warning("job %s: stage run %s of %s was closed meanwhile", job_id, info.run_id, stage)
        log.info(
            "job %s: stage %s %s in %.1f s (%d artifacts): %s",
            job_id, stage, status.value, float(marker.get("seconds") or 0), n, marker.get("summary"),
        )  # fmt: skip
        return {
            "stage": stage,
            "skipped": bool(marker.get("skipped")),
            "seconds": marker.get("seconds"),
            "summary": _json_safe(marker.get("summary")),
        }
    except JobStopped:
        _close_run(ctx, info.run_id, StageStatus.cancelled)
        raise
    except BaseException as e:
        _close_run(ctx, info.run_id, StageStatus.failed, error_text(None, e))
        raise


def stage_dir(stage: str) -> str:
    """The folder a stage owns (services.pipeline.REGISTRY), its name for a stage without one."""
    from services import pipeline

    sd = pipeline.REGISTRY.get(stage)
    return sd.dirs[0] if sd is not None and sd.dirs else stage


def prepare_fan_out(
    job_id: str, stage: str, *, settings: Settings, worker: str | None = None, node: str | None = None
) -> tuple[list[str], str]:
    """Start of a fan-out stage (services.pipeline.FanOut): open its stage run, do its preparation once
    (pushed, so that every unit task reuses it), return (the unit names, their queue); no units when the
    stage is up to date."""
    from services import pipeline

    fan = pipeline.REGISTRY[stage].fanout
    if fan is None:
        raise ValueError(f"stage {stage} is not a fan-out stage")
    ctx = get_context(settings)
    info = _begin(ctx, job_id, stage, worker, node=node)
    with captured(_keep_log(ctx, info)) as stage_log:
        return _prepare_fan_out(ctx, info, stage, fan, stage_log)


def _prepare_fan_out(
    ctx: Context, info: JobInfo, stage: str, fan: FanOut, stage_log: StageLog
) -> tuple[list[str], str]:
    from services import pipeline

    try:
        job = _materialize(ctx, info)
        report = ProgressReporter(ctx, info, stage_log=stage_log)
        if not info.forced and pipeline.is_done(job, stage):  # nothing to fan out: the stage task skips it
            report(stage, 0.0, "up to date")
            return [], fan.queue(job)
        report(stage, 0.0, "preparing the units")
        pipeline.check_inputs(job, stage)
        files = fan.prepare(job)
        _push(ctx, info, job, files, f"{stage}.prepare")
        names = fan.units(job)
        report(stage, 0.0, f"{len(names)} units to run")
        return names, fan.queue(job)
    except JobStopped:
        _close_run(ctx, info.run_id, StageStatus.cancelled)
        raise
    except BaseException as e:
        _close_run(ctx, info.run_id, StageStatus.failed, error_text(None, e))
        raise


def execute_unit(
    job_id: str, stage: str, unit: str, *, settings: Settings, worker: str | None = None
) -> dict:
    """One unit of a fan-out stage (a block, a view; it returns at once when already done); pushes its
    files and reports the stage's progress: the units done so far, and this one's own."""
    from services import pipeline

    fan = pipeline.REGISTRY[stage].fanout
    if fan is None:
        raise ValueError(f"stage {stage} is not a fan-out stage")
    ctx = get_context(settings)
    info = _begin(ctx, job_id, stage, worker, open_run=False)
    with captured(_keep_log(ctx, info)) as stage_log:
        return _execute_unit(ctx, info, stage, unit, fan, stage_log)


def _execute_unit(
    ctx: Context, info: JobInfo, stage: str, unit: str, fan: FanOut, stage_log: StageLog
) -> dict:
    job = _materialize(ctx, info)
    if not fan.ready(job):  # the preparation is missing here: do it
        fan.prepare(job)
    names = fan.units(job)
    reporter = ProgressReporter(ctx, info, stage_log=stage_log)

    def done() -> int:
        folder = fan.marker(unit).split("/", 1)[0] + "/"
        base = jobsync.files_key(info.prefix, "")
        keys = {k[len(base) :] for k in ctx.storage.list(jobsync.files_key(info.prefix, folder))}
        return sum(fan.marker(n) in keys for n in names)

    before = done()
    if info.forced:  # the unit's result from an earlier attempt is computed anew
        (job.root / fan.marker(unit)).unlink(missing_ok=True)
    t0 = time.perf_counter()
    set_threads(job)
    paths = fan.unit(job, unit, lambda f, m: reporter(stage, (before + f) / max(len(names), 1), m))
    seconds = time.perf_counter() - t0
    _push(ctx, info, job, paths, f"{stage}.unit.{unit}")
    reporter(stage, min(done(), len(names)) / max(len(names), 1), f"{unit} done")
    files = [Path(p).relative_to(job.root).as_posix() for p in paths]
    return {"stage": stage, "unit": unit, "files": files, "seconds": round(seconds, 2)}


def _json_safe(value: object) -> object:
    """NaN/inf -> None (PostgreSQL JSONB refuses them), recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def finalize(job_id: str, *, settings: Settings) -> dict:
    """The job succeeded: metrics = every stage's marker summary (read from storage) and the outcome
    (shared.outcome: registered images per set, warnings); webhook event.
    Idempotent (a job already succeeded is left as it is)."""
    from shared.webhooks import enqueue_job_event

    ctx = get_context(settings)
    with ctx.session() as s:
        row = crud.get_job(s, job_id)
        if row is not None and row.status == JobStatus.succeeded:
            return dict(row.metrics or {})
        info = _info(_live_row(s, job_id))
    metrics: dict[str, object] = {}
    for stage in info.stages:
        try:
            marker = json.loads(ctx.storage.get_bytes(jobsync.files_key(info.prefix, f"stages/{stage}.json")))
        except StorageKeyError:
            raise RuntimeError(f"stage {stage} has no marker in storage: it did not finish") from None
        metrics[stage] = _json_safe(marker.get("summary") or {})
    outcome = metrics["outcome"] = job_outcome(metrics)
    with ctx.session() as s:
        row = _live_row(s, job_id)
        crud.update_job_results(s, row, metrics=metrics)
        crud.set_job_status(s, row, JobStatus.succeeded)
        enqueue_job_event(s, row)
    if outcome["warnings"]:
        log.warning("job %s succeeded with warnings: %s", job_id, "; ".join(outcome["warnings"]))
    log.info("job %s succeeded: %s", job_id, metrics)
    return metrics


def fail(job_id: str, stage: str | None, error: BaseException | str, *, settings: Settings) -> None:
    """The job failed: its running stage runs and the job get the error text; webhook event. A job that
    has finished already (e.g. cancelled) is left as it is."""
    from shared.webhooks import enqueue_job_event

    text = error if isinstance(error, str) else error_text(stage, error)
    ctx = get_context(settings)
    with ctx.session() as s:
        row = crud.get_job(s, job_id)
        if row is None:
            return
        _close_running(s, job_id, StageStatus.failed, text)
        if row.status in TERMINAL_JOB_STATUSES:
            return
        crud.set_job_status(s, row, JobStatus.failed, error=text)
        enqueue_job_event(s, row)
    log.error("job %s failed: %s", job_id, text)


def _close_running(session: Session, job_id: str, status: StageStatus, error: str | None) -> int:
    runs = list(
        session.scalars(
            sa.select(StageRun).where(StageRun.job_id == job_id, StageRun.status == StageStatus.running)
        )
    )
    for run in runs:
        crud.finish_stage(session, run, status, error=error)
    return len(runs)


def close_running_stages(
    job_id: str, *, settings: Settings, status: StageStatus = StageStatus.cancelled
) -> int:
    """Close the job's running stage runs (after its tasks were terminated on cancel)."""
    with get_context(settings).session() as s:
        return _close_running(s, job_id, status, None)


def job_stage_list(job_id: str, *, settings: Settings, from_stage: str | None = None) -> list[str]:
    """The job's stages from from_stage on (JobStopped when it no longer runs)."""
    ctx = get_context(settings)
    with ctx.session() as s:
        row = crud.get_job(s, job_id)
        if row is None:
            raise JobStopped(f"job {job_id} no longer exists")
        return JobOptions.model_validate(row.options or {}).stages_from(from_stage)


__all__ = [
    "JobStopped",
    "execute_unit",
    "execute_stage",
    "fail",
    "finalize",
    "heartbeat",
    "is_transient",
    "prepare_fan_out",
]
