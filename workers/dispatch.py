"""CeleryDispatcher: a job's stages as a Celery canvas over the gpu/cpu/reduce queues.

    stages without a fan-out stage:  chain(run_stage(s1), ..., run_stage(sN), finalize)
    with one (FANOUT_STAGES):        chain(run_stage(s) for s before it, fan_out(it, stages after it))

fan_out (workers/tasks.py) replaces itself at run time, once the stage's units are known (the blocks
once planned, the views once rendered), by chord([stage_unit(u) ...], chain(run_stage(it), canvas of
the stages after it)): a later fan-out stage fans out the same way.

Signatures are built by task name on an app configured from the given settings, so that the API process
never imports the task module (nor the pipeline behind it).
"""

from __future__ import annotations

import logging
from typing import Any

from celery import Celery, chain

from services.pipeline import FANOUT_STAGES, STAGE_QUEUES
from workers.celery_app import (
    FAN_OUT,
    FINALIZE,
    RUN_STAGE,
    TASK_QUEUES,
    TASKS_TTL_S,
    make_app,
    redis_url,
    tasks_key,
)

log = logging.getLogger("midview.workers.dispatch")


def build_canvas(app: Celery, job_id: str, stages: list[str]) -> Any:
    """The canvas of a job's stages (in pipeline order, as JobOptions.stages_from gives them)."""
    if not stages:
        raise ValueError("no stages to run")
    return chain(*canvas_steps(app, job_id, stages))


def canvas_steps(app: Celery, job_id: str, stages: list[str]) -> list[Any]:
    """run_stage of each stage up to the first fan-out stage, then fan_out(it, the rest); finalize last
    when there is none (no stages: finalize alone)."""

    def sig(name: str, *args: Any, queue: str) -> Any:
        return app.signature(name, args=args, immutable=True, queue=queue)

    for i, s in enumerate(stages):
        if s in FANOUT_STAGES:
            head = [sig(RUN_STAGE, job_id, x, queue=STAGE_QUEUES[x]) for x in stages[:i]]
            return [*head, sig(FAN_OUT, job_id, s, list(stages[i + 1 :]), queue=STAGE_QUEUES[s])]
    head = [sig(RUN_STAGE, job_id, x, queue=STAGE_QUEUES[x]) for x in stages]
    return [*head, sig(FINALIZE, job_id, queue=TASK_QUEUES[FINALIZE])]


class CeleryDispatcher:
    """shared.dispatch.Dispatcher over Celery; settings give the broker, result backend and database."""

    def __init__(self, settings: Any, app: Celery | None = None):
        self.settings = settings
        self._own_app = app is None
        self.app = app or make_app(settings, name="midview-dispatch", set_as_current=False)
        self._redis: Any = None
        self._profile: tuple[float, str] | None = None  # (when read, the workers' profile)

    # bookkeeping in Redis (workers/tasks.py uses the same keys)
    def redis(self) -> Any:
        if self._redis is None:
            import redis

            url = redis_url(self.settings)
            self._redis = (
                redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5) if url else False
            )
        return self._redis or None

    def profile(self, max_age_s: float = 10.0) -> str:
        """The job profile the workers offer (workers.offer), read from Redis when the last read is older
        than max_age_s."""
        import time

        from workers.offer import profile_of, read_offers

        now = time.monotonic()
        if self._profile is not None and now - self._profile[0] < max_age_s:
            return self._profile[1]
        import redis

        r = self.redis()
        try:
            profile = profile_of(read_offers(r)) if r is not None else "cpu"
        except redis.RedisError as e:  # no word from the workers: the profile every worker runs
            log.warning("could not read the workers' offers: %s", e)
            profile = "cpu"
        self._profile = (now, profile)
        return profile

    def canvas(self, job_id: str, from_stage: str | None = None) -> Any:
        from workers.execute import job_stage_list

        stages = job_stage_list(job_id, settings=self.settings, from_stage=from_stage)
        return build_canvas(self.app, job_id, stages)

    def submit(self, job_id: str, from_stage: str | None = None) -> str | None:
        """Queue the job's stages (from from_stage on); returns the id of the chain's first task."""
        result = self.canvas(job_id, from_stage).apply_async()
        ids = []
        r = result
        while r is not None:
            ids.append(r.id)
            r = r.parent
        root = ids[-1]
        self._remember(job_id, ids)
        log.info("job %s: queued from %s (root task %s)", job_id, from_stage or "the start", root)
        return root

    def _remember(self, job_id: str, ids: list[str]) -> None:
        import redis

        r = self.redis()
        if r is None:
            return
        try:
            r.pipeline().sadd(tasks_key(job_id), *ids).expire(tasks_key(job_id), TASKS_TTL_S).execute()
        except redis.RedisError as e:
            log.warning("job %s: could not record its task ids: %s", job_id, e)

    def task_ids(self, job_id: str) -> list[str]:
        r = self.redis()
        return sorted(x.decode() for x in r.smembers(tasks_key(job_id))) if r is not None else []

    def revoke(self, job_id: str) -> None:
        """Revoke the job's queued tasks and terminate its running ones (the tasks also check the job's
        status when they start and at every progress report)."""
        ids = set(self.task_ids(job_id))
        try:
            from shared.db.models import Job
            from shared.db.session import get_engine, session_scope

            with session_scope(get_engine(self.settings.database_url)) as s:
                row = s.get(Job, job_id)
                if row is not None and row.celery_root_id:
                    ids.add(row.celery_root_id)
        except Exception:
            log.exception("job %s: could not read its root task id", job_id)
        if ids:
            # SIGKILL: the running task is native code (pycolmap, torch) that cannot stop cleanly, and
            # pycolmap's glog failure handler catches SIGTERM to print a stack trace, which can deadlock
            # inside malloc (a cancel left the pool process hung); the database is the source of truth
            self.app.control.revoke(sorted(ids), terminate=True, signal="SIGKILL")
            log.info("job %s: revoked %d tasks", job_id, len(ids))
        try:  # a terminated task cannot close its stage run itself
            from shared.db.models import Job, JobStatus
            from workers.execute import close_running_stages, get_context

            with get_context(self.settings).session() as s:
                row = s.get(Job, job_id)
                cancelled = row is not None and row.status == JobStatus.cancelled
            if cancelled:
                close_running_stages(job_id, settings=self.settings)
        except Exception:
            log.exception("job %s: could not close its running stage runs", job_id)

    def close(self) -> None:
        if self._redis:
            self._redis.close()
        if self._own_app:
            self.app.close()
