"""The reconciler: compares the jobs the database says are queued or running with what is being worked
on, and dispatches again the jobs that stalled (a lost message, a worker that died for good, an API
that crashed between committing a job and queueing it).

A job is stalled when its last sign of life in the database (created, started, a stage run started or
finished) is older than stall_timeout_s AND nothing works on it: `is_live(job_id)` is false. In the
Celery deployment RedisLiveness answers that: a task of the job runs (its heartbeat key exists), or a
message of the job waits in a queue or is reserved by a worker. Stages are idempotent (a stage whose
outputs are up to date is skipped), so dispatching a job twice costs time, never correctness.

- running -> submit(job_id, from_stage=job.current_stage);
- queued  -> submit(job_id) (without a liveness probe: only when no root task id was recorded).

A worker node that dies as a whole (machine lost, container killed) leaves the messages it had reserved
in the broker's `unacked` hash until the visibility timeout (hours), so RedisLiveness still counts its
jobs as live. `nodes` (NodeCheck, the Celery deployment) catches that early: a running stage run whose
heartbeat (refreshed every heartbeat_every_s by the task working on it, workers/tasks.py) is older than
heartbeat_timeout_s, and whose Celery node does not answer a ping, or whose heartbeat is older than
heartbeat_dead_s whatever the node says, is closed as failed ("abandoned") and its job dispatched again
from that stage, unless a task of the job runs or a message of it waits in a queue (`active`).
A broker that restarted (Redis crashed; its memory lost) loses the messages and the task keys; the
worker, reconnected, answers pings, and its task was cancelled on the connection loss: a stale heartbeat
whose job the broker holds nothing of (`known`: running, queued or reserved) is given up the same way.
The same loss between two stages (the next stage's message waited in a queue) leaves a job with no
stage running: when the broker was read, such a job that has shown no sign of life for
heartbeat_timeout_s and of which the broker holds nothing is dispatched again at once (from its current
stage, skipped if up to date), not after stall_timeout_s; likewise a queued job whose first message
was lost.

`reconcile` returns the actions it took (and logs them), so that it can be tested on database rows with
a recording dispatcher.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Container
from dataclasses import asdict, dataclass
from datetime import datetime, timedelta
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from services.pipeline import JobOptions
from shared.db import crud
from shared.db.models import Job, JobStatus, StageRun, StageStatus, utcnow

log = logging.getLogger("midview.workers.reconcile")

_UUID = re.compile(rb"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")


@dataclass
class Action:
    job_id: str
    status: str  # the job's status when it was found stalled
    from_stage: str | None
    reason: str
    task_id: str | None = None
    error: str | None = None  # the dispatch failed (tried again at the next pass)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def last_activity(session: Session, job: Job) -> datetime:
    """The job's last sign of life in the database: created, started, a stage run started or finished."""
    row = session.execute(
        sa.select(sa.func.max(StageRun.started_at), sa.func.max(StageRun.finished_at)).where(
            StageRun.job_id == job.id
        )
    ).one()
    stamps = [job.created_at, job.started_at, *row]
    return max(_aware(t) for t in stamps if t is not None)


def _aware(t: datetime) -> datetime:
    from datetime import UTC

    return t.replace(tzinfo=UTC) if t.tzinfo is None else t


LiveProbe = Callable[[str], bool] | Container[str] | None


@dataclass
class NodeCheck:
    """How the reconciler tells that the worker node running a stage died (see the module)."""

    ping: Callable[[list[str]], set[str]]  # the nodes among these that answer
    heartbeat_timeout_s: float = 120.0
    heartbeat_dead_s: float = 1800.0
    active: Container[str] = frozenset()  # jobs with a running task or a message waiting in a queue
    # jobs the broker holds anything of (running, queued or reserved); None: the broker was not read
    known: Container[str] | None = None


def celery_ping(app: Any, timeout_s: float = 2.0) -> Callable[[list[str]], set[str]]:
    """NodeCheck.ping over Celery's remote control: the names of the nodes that answer."""

    def ping(nodes: list[str]) -> set[str]:
        replies = app.control.ping(destination=list(nodes), timeout=timeout_s) or []
        return {name for reply in replies for name in reply}

    return ping


def _stale_runs(session: Session, now: datetime, timeout_s: float) -> list[StageRun]:
    """Running stage runs of running jobs whose last heartbeat (or start) is older than timeout_s."""
    cutoff = now - timedelta(seconds=float(timeout_s))
    last = sa.func.coalesce(StageRun.heartbeat_at, StageRun.started_at)
    stmt = (
        sa.select(StageRun)
        .join(Job, Job.id == StageRun.job_id)
        .where(Job.status == JobStatus.running, StageRun.status == StageStatus.running, last < cutoff)
        .order_by(StageRun.started_at)
    )
    return list(session.scalars(stmt))


def lost_runs(session: Session, now: datetime, nodes: NodeCheck) -> dict[str, tuple[StageRun, str]]:
    """job id -> (a running stage run whose worker is lost, why), see the module."""
    stale = [r for r in _stale_runs(session, now, nodes.heartbeat_timeout_s) if r.job_id not in nodes.active]
    names = sorted({r.node for r in stale if r.node})
    answering: set[str] | None = set()
    if names:
        try:
            answering = nodes.ping(names)
        except Exception:  # no verdict on the nodes this time; very old heartbeats still count
            log.exception("could not ping the worker nodes %s", names)
            answering = None
    out: dict[str, tuple[StageRun, str]] = {}
    for run in stale:
        age = (now - _aware(run.heartbeat_at or run.started_at)).total_seconds()
        if age >= nodes.heartbeat_dead_s:
            why = f"stage {run.stage}: no heartbeat for {age:.0f} s"
        elif run.node and answering is not None and run.node not in answering:
            why = f"stage {run.stage}: no heartbeat for {age:.0f} s and its node {run.node} does not answer"
        elif nodes.known is not None and run.job_id not in nodes.known:
            why = (
                f"stage {run.stage}: no heartbeat for {age:.0f} s and no task or message of it in the broker"
            )
        else:
            continue
        out.setdefault(run.job_id, (run, why))
    return out


def _message_lost(
    session: Session, job: Job, now: datetime, last: datetime, nodes: NodeCheck | None
) -> str | None:
    """Why the job's next message is lost (see the module), or None: the broker was read and holds
    nothing of the job, no stage of it runs, and it has been idle for the heartbeat timeout (longer than
    the moment between a task's end and its successor's message)."""
    if nodes is None or nodes.known is None or job.id in nodes.known:
        return None
    idle = (now - last).total_seconds()
    if idle < nodes.heartbeat_timeout_s:
        return None
    running = session.scalar(
        sa.select(sa.func.count())
        .select_from(StageRun)
        .where(StageRun.job_id == job.id, StageRun.status == StageStatus.running)
    )
    if running:
        return None  # a stage run without its task: lost_runs decides (its heartbeat, its node)
    return f"{job.status.value}, no stage running for {idle:.0f} s and no task or message of it in the broker"


def _probe(is_live: LiveProbe) -> Callable[[str], bool | None]:
    if is_live is None:
        return lambda job_id: None
    if callable(is_live):
        return lambda job_id: bool(is_live(job_id))
    return lambda job_id: job_id in is_live


def reconcile(
    session: Session,
    dispatcher: Any,
    now: datetime | None = None,
    stall_timeout_s: float = 900.0,
    *,
    is_live: LiveProbe = None,
    limit: int = 100,
    nodes: NodeCheck | None = None,
) -> list[Action]:
    """Dispatch again the queued and running jobs that stalled, and the running jobs whose stage lost
    its worker node when `nodes` is given (see the module); returns the actions. The caller commits (new
    root task ids and closed stage runs are written)."""
    now = now or utcnow()
    cutoff = now - timedelta(seconds=float(stall_timeout_s))
    live = _probe(is_live)
    lost = lost_runs(session, now, nodes) if nodes is not None else {}
    stmt = (
        sa.select(Job)
        .where(Job.status.in_([JobStatus.queued, JobStatus.running]))
        .order_by(Job.created_at)
        .limit(limit)
        .with_for_update(skip_locked=True, of=Job)  # two reconcilers never take the same job
    )
    actions: list[Action] = []
    for job in session.scalars(stmt):
        stages = JobOptions.model_validate(job.options or {}).stages
        if job.id in lost:
            run, why = lost[job.id]
            crud.finish_stage(session, run, StageStatus.failed, error=f"abandoned: {why}")
            from_stage = run.stage if run.stage in stages else None
            actions.append(_dispatch(session, dispatcher, job, from_stage, f"worker lost: {why}"))
            continue
        last = last_activity(session, job)
        message_lost = _message_lost(session, job, now, last, nodes)
        if message_lost is not None:
            from_stage = job.current_stage if job.current_stage in stages else None
            actions.append(_dispatch(session, dispatcher, job, from_stage, message_lost))
            continue
        if last > cutoff:
            continue
        alive = live(job.id)
        if alive:
            continue
        idle = (now - last).total_seconds()
        if job.status == JobStatus.queued:
            if alive is None and job.celery_root_id:
                continue  # its first task may still wait in a queue: without a probe we cannot tell
            from_stage, reason = None, f"queued for {idle:.0f} s and not in any queue"
        else:
            from_stage = job.current_stage if job.current_stage in stages else None
            reason = f"running, no sign of life for {idle:.0f} s and no live task"
        actions.append(_dispatch(session, dispatcher, job, from_stage, reason))
    session.flush()
    return actions


def _dispatch(session: Session, dispatcher: Any, job: Job, from_stage: str | None, reason: str) -> Action:
    """Submit the job again from from_stage; the action taken (with the error when the dispatch failed,
    to be tried again at the next pass)."""
    action = Action(job.id, job.status.value, from_stage, reason)
    try:
        task_id = dispatcher.submit(job.id, from_stage)
        if isinstance(task_id, str) and task_id:
            action.task_id = task_id
            crud.update_job_results(session, job, celery_root_id=task_id)
        log.warning("job %s %s: dispatched again from %s", job.id, reason, from_stage or "the start")
    except Exception as e:
        action.error = f"{type(e).__name__}: {e}"
        log.exception("job %s %s: dispatching it again failed", job.id, reason)
    return action


@dataclass
class LiveParts:
    """Job ids by where RedisLiveness saw them."""

    running: set[str]  # a task of the job runs (its heartbeat key exists)
    queued: set[str]  # a message of the job waits in a queue
    reserved: set[str]  # a message of the job is reserved by a worker (unacked), maybe a dead one

    def all(self) -> set[str]:
        return self.running | self.queued | self.reserved


class RedisLiveness:
    """Which jobs Celery is working on, from Redis: a task of the job running (heartbeat key, see
    workers/tasks.py), or a message naming the job waiting in a queue or reserved by a worker (the Redis
    transport's `unacked` hash). `snapshot()` reads it all once: a set of job ids; `parts()` keeps the
    three apart."""

    def __init__(self, redis: Any, queues: tuple[str, ...] | None = None, priority_steps: int = 10):
        from workers.celery_app import ALIVE_PATTERN, QUEUES

        self.redis = redis
        self.queues = queues or QUEUES
        self.priority_steps = priority_steps
        self.alive_pattern = ALIVE_PATTERN

    def _queue_keys(self) -> list[str]:
        sep = "\x06\x16"  # kombu's priority queue suffix
        return [q for name in self.queues for q in (name, *(f"{name}{sep}{p}" for p in range(1, 10)))]

    def _running(self) -> set[str]:
        import json

        live: set[str] = set()
        for key in self.redis.scan_iter(match=self.alive_pattern, count=500):
            raw = self.redis.get(key)
            if raw:
                try:
                    live.add(str(json.loads(raw)["job"]))
                except (ValueError, KeyError, TypeError):
                    continue
        return live

    @staticmethod
    def _ids(blobs: list[bytes]) -> set[str]:
        return {m.decode() for blob in blobs for m in _UUID.findall(blob)}  # task ids too: harmless

    def parts(self) -> LiveParts:
        blobs: list[bytes] = []
        for q in self._queue_keys():
            blobs += self.redis.lrange(q, 0, -1)
        return LiveParts(self._running(), self._ids(blobs), self._ids(self.redis.hvals("unacked")))

    def snapshot(self) -> set[str]:
        return self.parts().all()

    def __call__(self, job_id: str) -> bool:
        return job_id in self.snapshot()
