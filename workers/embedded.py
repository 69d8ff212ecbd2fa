"""EmbeddedDispatcher: the single-machine default (`midview serve`): one background thread of the API
process runs the jobs one after the other, through the same workers.execute functions as the Celery
tasks (stages in order; the units of a fan-out stage one by one), with the same retry policy for transient
errors. A second thread delivers webhooks and runs the reconciler, which also resumes, at start, the
jobs a previous process left queued or running.

One process only: two processes with an embedded dispatcher on one database would both resume the
same jobs.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from services.pipeline import FANOUT_STAGES
from workers import execute

log = logging.getLogger("midview.workers.embedded")

WEBHOOKS_EVERY_S = 15.0
RECONCILE_EVERY_S = 60.0


class EmbeddedDispatcher:
    """shared.dispatch.Dispatcher running jobs in a thread of this process."""

    def __init__(self, settings: Any, start: bool = True, resume: bool = True):
        self.settings = settings
        self._queue: queue.Queue[tuple[str, str | None] | None] = queue.Queue()
        self._lock = threading.Lock()
        self._known: set[str] = set()  # queued here or running here
        self._cancelled: set[str] = set()
        self._stop = threading.Event()
        self._resume = resume
        self.current: str | None = None
        self._runner = threading.Thread(target=self._run_loop, name="midview-embedded-runner", daemon=True)
        self._ticker = threading.Thread(target=self._tick_loop, name="midview-embedded-ticker", daemon=True)
        if start:
            self.start()

    # Dispatcher
    def profile(self) -> str:
        """The embedded worker runs the cpu profile (services.pipeline.PROFILES)."""
        return "cpu"

    def submit(self, job_id: str, from_stage: str | None = None) -> str | None:
        with self._lock:
            self._cancelled.discard(job_id)
            self._known.add(job_id)
        self._queue.put((job_id, from_stage))
        log.info("job %s: queued (embedded) from %s", job_id, from_stage or "the start")
        return None

    def revoke(self, job_id: str) -> None:
        """Stop the job at its next stage boundary or progress report (the row says cancelled)."""
        with self._lock:
            self._cancelled.add(job_id)

    # life cycle
    def start(self) -> None:
        if not self._runner.is_alive():
            self._runner.start()
        if not self._ticker.is_alive():
            self._ticker.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop both threads; a stage that is running finishes in the background (daemon thread)."""
        self._stop.set()
        self._queue.put(None)
        for t in (self._runner, self._ticker):
            if t.is_alive():
                t.join(timeout)

    def idle(self) -> bool:
        """Nothing queued or running."""
        with self._lock:
            return not self._known

    def wait_idle(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.idle():
                return True
            time.sleep(0.1)
        return self.idle()

    def is_live(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._known

    # runner
    def _run_loop(self) -> None:
        while not self._stop.is_set():
            item = self._queue.get()
            if item is None:
                break
            job_id, from_stage = item
            self.current = job_id
            try:
                self.run_job(job_id, from_stage)
            except Exception:  # never let the thread die
                log.exception("job %s: unexpected error in the embedded runner", job_id)
            finally:
                self.current = None
                with self._lock:
                    if not any(item and item[0] == job_id for item in list(self._queue.queue)):
                        self._known.discard(job_id)

    def _check(self, job_id: str) -> None:
        if self._stop.is_set():
            raise execute.JobStopped("the dispatcher is shutting down")
        with self._lock:
            if job_id in self._cancelled:
                raise execute.JobStopped(f"job {job_id} was cancelled")

    def _call(self, job_id: str, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args, settings=...) with retries of transient errors (exponential back-off)."""
        retries = 0
        while True:
            self._check(job_id)
            try:
                return fn(*args, settings=self.settings)
            except execute.JobStopped:
                raise
            except Exception as e:
                if not execute.is_transient(e) or retries >= self.settings.task_max_retries:
                    raise
                delay = execute.backoff_s(retries)
                retries += 1
                log.warning("job %s: %s: transient error (%s); retry %d in %.0f s", job_id, fn.__name__, e,
                            retries, delay)  # fmt: skip
                if self._stop.wait(delay):
                    raise execute.JobStopped("the dispatcher is shutting down") from e

    def run_job(self, job_id: str, from_stage: str | None = None) -> None:
        """The job's stages in order, then finalize; a failure fails the job (execute.fail)."""
        stage: str | None = None
        try:
            stages = execute.job_stage_list(job_id, settings=self.settings, from_stage=from_stage)
            for stage in stages:
                if stage in FANOUT_STAGES:
                    units, _ = self._call(job_id, execute.prepare_fan_out, job_id, stage)
                    for unit in units:
                        self._call(job_id, execute.execute_unit, job_id, stage, unit)
                self._call(job_id, execute.execute_stage, job_id, stage)
            stage = None
            self._call(job_id, execute.finalize, job_id)
        except execute.JobStopped as e:
            log.info("job %s stopped: %s", job_id, e)
        except Exception as e:
            log.exception("job %s failed in stage %s", job_id, stage)
            try:
                execute.fail(job_id, stage, e, settings=self.settings)
            except Exception:
                log.exception("job %s: could not record the failure", job_id)

    # webhooks and reconciler
    def _tick_loop(self) -> None:
        next_hooks = 0.0
        next_reconcile = 0.0
        first = True
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_reconcile:
                self.reconcile(stall_timeout_s=0.0 if first and self._resume else None)
                first = False
                next_reconcile = now + RECONCILE_EVERY_S
            if now >= next_hooks:
                self.deliver_webhooks()
                next_hooks = now + WEBHOOKS_EVERY_S
            self._stop.wait(max(0.1, min(next_hooks, next_reconcile) - time.monotonic()))

    def reconcile(self, stall_timeout_s: float | None = None) -> list:
        """Resubmit the queued/running jobs that this dispatcher does not know and that stalled (at
        start: all of them, left over by a previous process)."""
        from shared.db.models import utcnow
        from workers.reconcile import reconcile

        timeout = self.settings.stall_timeout_s if stall_timeout_s is None else stall_timeout_s
        try:
            with execute.get_context(self.settings).session() as s:
                return reconcile(s, self, utcnow(), timeout, is_live=self.is_live)
        except Exception:
            log.exception("embedded reconcile failed")
            return []

    def deliver_webhooks(self) -> int:
        from shared.netguard import parse_networks
        from shared.webhooks import deliver_due

        try:
            with execute.get_context(self.settings).session() as s:
                return deliver_due(s, allow=parse_networks(self.settings.webhook_allow_networks))
        except Exception:
            log.exception("webhook delivery failed")
            return 0
