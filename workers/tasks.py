"""Celery tasks: thin wrappers over workers.execute with the service's error policy.

- run_stage(job_id, stage): one pipeline stage (queue: STAGE_QUEUES[stage]);
- fan_out(job_id, stage, after): prepares a fan-out stage (train_blocks, match_views), then replaces
  itself by chord([stage_unit(job_id, stage, u) for each unit], chain(run_stage(stage), canvas of after));
- stage_unit(job_id, stage, unit): one unit of a fan-out stage (a block, a view; its queue set by the
  fan-out: services.pipeline.FanOut.queue);
- finalize(job_id): the job succeeded;
- reconcile(), deliver_webhooks(): periodic (celery beat).

Errors: a transient error (connections of the database, storage, Redis; see execute.is_transient) is
retried with exponential back-off and jitter, at most settings.task_max_retries times; any other error
marks the stage and the job failed (execute.fail) and is re-raised, which stops the chain. A job that was
cancelled or finished meanwhile (execute.JobStopped) ends the task with celery's Ignore: no callback
runs, nothing is recorded as failed.

While a task of a job runs, its id is in the Redis set `midview:job:{job}:tasks` (the dispatcher revokes
them on cancel) and `midview:task:{id}:alive` holds {job, task, args, pid, hostname}, refreshed every
settings.heartbeat_every_s with a TTL of alive_ttl_s: the reconciler's proof that the job is being
worked on. Every heartbeat_every_s the task also refreshes `heartbeat_at` of its stage run in the
database; the run records the task's Celery node, which the reconciler pings when that heartbeat gets
old (a worker node that died).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from celery import chain, chord
from celery.exceptions import Ignore, Reject, Retry

from services.pipeline import STAGE_QUEUES
from shared.config import get_settings
from workers import execute
from workers.celery_app import (
    ALIVE_PATTERN,
    DELIVER_WEBHOOKS,
    FAN_OUT,
    FINALIZE,
    RECONCILE,
    RUN_STAGE,
    STAGE_UNIT,
    TASKS_TTL_S,
    alive_key,
    app,
    redis_url,
    tasks_key,
)

log = logging.getLogger("midview.workers.tasks")


__all__ = ["ALIVE_PATTERN", "alive_key", "tasks_key"]

# -- Redis ---------------------------------------------------------------------------------------
_redis: Any = None
_redis_pid: int | None = None


def alive_ttl_s(heartbeat_every_s: float) -> int:
    """TTL of a task's heartbeat key: three beats (two missed ones, a slow Redis, do not make it vanish);
    no longer than the reconciler's heartbeat timeout at the defaults, so a dead task's key is gone by
    the time its stage run's heartbeat is stale."""
    return max(3, math.ceil(3 * heartbeat_every_s))


def redis_client() -> Any:
    """This process's Redis client (None when no Redis is configured)."""
    global _redis, _redis_pid
    if _redis is None or _redis_pid != os.getpid():
        import redis

        url = redis_url(get_settings())
        _redis = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5) if url else None
        _redis_pid = os.getpid()
    return _redis


def reset_clients() -> None:
    """Forget clients created before a fork."""
    global _redis, _redis_pid
    _redis, _redis_pid = None, None


def _db_heartbeat(job_id: str, stage: str | None) -> None:
    """Refresh the stage run's heartbeat in the database; trouble is logged, never fatal."""
    if stage is None:
        return
    try:
        execute.heartbeat(job_id, stage, settings=get_settings())
    except Exception as e:
        log.warning("database heartbeat of job %s stage %s: %s", job_id, stage, e)


@contextmanager
def tracked(task: Any, job_id: str, stage: str | None = None) -> Iterator[None]:
    """Register the running task in Redis (task set of the job, heartbeat key) for its duration, and
    keep the heartbeat of its stage run fresh in the database; Redis or database trouble here is logged,
    never fatal."""
    import redis

    r = redis_client()
    tid = task.request.id
    info = json.dumps(
        {
            "job": job_id,
            "task": task.name,
            "args": list(task.request.args or []),
            "pid": os.getpid(),
            "hostname": task.request.hostname,
            "started": time.time(),
        }
    )
    in_redis = r is not None and bool(tid)
    stop = threading.Event()
    every_s = get_settings().heartbeat_every_s
    ttl_s = alive_ttl_s(every_s)

    def heartbeat() -> None:
        while not stop.wait(every_s):
            if in_redis:
                try:
                    r.set(alive_key(tid), info, ex=ttl_s)
                except redis.RedisError as e:
                    log.warning("heartbeat of task %s: %s", tid, e)
            _db_heartbeat(job_id, stage)

    if in_redis:
        try:
            pipe = r.pipeline()
            pipe.sadd(tasks_key(job_id), tid).expire(tasks_key(job_id), TASKS_TTL_S)
            pipe.set(alive_key(tid), info, ex=ttl_s)
            pipe.execute()
        except redis.RedisError as e:
            log.warning("could not register task %s of job %s: %s", tid, job_id, e)
    beat = threading.Thread(target=heartbeat, name=f"heartbeat-{tid}", daemon=True)
    beat.start()
    try:
        yield
    finally:
        stop.set()
        if in_redis:
            try:
                r.pipeline().srem(tasks_key(job_id), tid).delete(alive_key(tid)).execute()
            except redis.RedisError as e:
                log.warning("could not unregister task %s of job %s: %s", tid, job_id, e)


# -- error policy --------------------------------------------------------------------------------
def _guarded(task: Any, job_id: str, stage: str | None, fn: Callable[[Any], Any]) -> Any:
    settings = get_settings()
    try:
        with tracked(task, job_id, stage):
            return fn(settings)
    except execute.JobStopped as e:
        log.info("job %s: %s stopped: %s", job_id, task.name, e)
        raise Ignore() from None
    except (Ignore, Reject, Retry):
        raise
    except Exception as e:
        retries = int(task.request.retries or 0)
        if execute.is_transient(e) and retries < settings.task_max_retries:
            delay = execute.backoff_s(retries)
            log.warning(
                "job %s: %s failed with a transient error (%s: %s); retry %d/%d in %.0f s",
                job_id, task.name, type(e).__name__, e, retries + 1, settings.task_max_retries, delay,
            )  # fmt: skip
            raise task.retry(exc=e, countdown=delay, max_retries=settings.task_max_retries) from e
        log.exception("job %s: %s failed", job_id, task.name)
        try:
            execute.fail(job_id, stage, e, settings=settings)
        except Exception:
            log.exception("job %s: could not record the failure", job_id)
        raise


# -- canvas --------------------------------------------------------------------------------------
def stage_sig(job_id: str, stage: str) -> Any:
    return run_stage.si(job_id, stage).set(queue=STAGE_QUEUES[stage])


def fan_out_canvas(job_id: str, stage: str, units: list[str], queue: str, after: list[str]) -> Any:
    """chord(one stage_unit per unit, on `queue`) -> run_stage(stage) -> the canvas of the stages after."""
    from workers.dispatch import canvas_steps

    body = chain(stage_sig(job_id, stage), *canvas_steps(app, job_id, after))
    if not units:
        return body
    return chord([stage_unit.si(job_id, stage, u).set(queue=queue) for u in units], body)


# -- tasks ---------------------------------------------------------------------------------------
@app.task(bind=True, name=RUN_STAGE)
def run_stage(self: Any, job_id: str, stage: str) -> dict:
    """One pipeline stage of a job."""
    worker, node = f"{self.request.hostname}:{os.getpid()}", self.request.hostname
    return _guarded(
        self,
        job_id,
        stage,
        lambda s: execute.execute_stage(job_id, stage, settings=s, worker=worker, node=node),
    )


@app.task(bind=True, name=STAGE_UNIT)
def stage_unit(self: Any, job_id: str, stage: str, unit: str) -> dict:
    """One unit of a fan-out stage (a block of train_blocks, a view of match_views)."""
    worker = f"{self.request.hostname}:{os.getpid()}"
    return _guarded(
        self, job_id, stage, lambda s: execute.execute_unit(job_id, stage, unit, settings=s, worker=worker)
    )


@app.task(bind=True, name=FAN_OUT)
def fan_out(self: Any, job_id: str, stage: str, after: list[str]) -> Any:
    """Prepare a fan-out stage once (the blocks' plan, the matching features), then replace this task by
    the chord of its units followed by the stage's own run and the stages `after` it."""
    worker, node = f"{self.request.hostname}:{os.getpid()}", self.request.hostname
    units, queue = _guarded(
        self,
        job_id,
        stage,
        lambda s: execute.prepare_fan_out(job_id, stage, settings=s, worker=worker, node=node),
    )
    log.info("job %s: fanning out %d units of %s on %s, then %s", job_id, len(units), stage, queue, after)
    raise self.replace(fan_out_canvas(job_id, stage, list(units), queue, list(after)))


@app.task(bind=True, name=FINALIZE)
def finalize(self: Any, job_id: str) -> dict:
    """The job succeeded: status, metrics, webhook event."""
    return _guarded(self, job_id, None, lambda s: execute.finalize(job_id, settings=s))


@app.task(name=RECONCILE)
def reconcile() -> list[dict]:
    """Re-dispatch jobs that stalled, or whose running stage lost its worker node (see workers.reconcile)."""
    from shared.db.models import utcnow
    from shared.db.session import get_engine, session_scope
    from workers.dispatch import CeleryDispatcher
    from workers.reconcile import NodeCheck, RedisLiveness, celery_ping
    from workers.reconcile import reconcile as run_reconcile

    settings = get_settings()
    r = redis_client()
    parts = RedisLiveness(r).parts() if r is not None else None
    nodes = NodeCheck(
        ping=celery_ping(app),
        heartbeat_timeout_s=settings.heartbeat_timeout_s,
        heartbeat_dead_s=settings.heartbeat_dead_s,
        active=parts.running | parts.queued if parts is not None else frozenset(),
        known=parts.all() if parts is not None else None,
    )
    with session_scope(get_engine(settings.database_url)) as session:
        actions = run_reconcile(
            session,
            CeleryDispatcher(settings, app=app),
            utcnow(),
            settings.stall_timeout_s,
            is_live=parts.all() if parts is not None else None,
            nodes=nodes,
        )
    return [a.as_dict() for a in actions]


@app.task(name=DELIVER_WEBHOOKS)
def deliver_webhooks() -> int:
    """Send the webhook deliveries that are due."""
    from shared.db.session import get_engine, session_scope
    from shared.webhooks import deliver_due

    with session_scope(get_engine(get_settings().database_url)) as session:
        return deliver_due(session)
