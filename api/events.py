"""Server-sent events of a job's progress: the job row is polled, every change is sent, the stream ends
when the job reaches a final status.

The streams of an API process share one poll (JobWatch): every poll_s one query reads all the jobs
being followed, whatever the number of streams, so a burst of streams costs the database pool nothing
more than one connection now and then (each new stream reads its job once, at once)."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import anyio
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from shared.db.models import TERMINAL_JOB_STATUSES, Job


def job_snapshot(job: Job) -> dict[str, Any]:
    """What the event stream reports of a job (JSON-ready)."""
    return {
        "id": job.id,
        "status": job.status.value,
        "stage": job.current_stage,
        "progress": job.progress,
        "progress_percent": round(100.0 * job.progress, 1),
        "message": job.progress_message,
        "attempt": job.attempt,
        "error": job.error,
        "timings": job.timings or {},
        "metrics": job.metrics or {},
        "outcome": (job.metrics or {}).get("outcome"),
        "started_at": job.started_at.isoformat() if job.started_at else None,
        "finished_at": job.finished_at.isoformat() if job.finished_at else None,
    }


def _load(make_session: sessionmaker[Session], job_ids: list[str]) -> dict[str, dict[str, Any]]:
    """The snapshots of the jobs that exist among job_ids, in one query."""
    with make_session() as session:
        jobs = session.scalars(sa.select(Job).where(Job.id.in_(job_ids)))
        return {job.id: job_snapshot(job) for job in jobs}


class JobWatch:
    """The jobs that this process's event streams follow, polled together (see the module)."""

    def __init__(self, make_session: sessionmaker[Session], poll_s: float = 0.5):
        self.make_session, self.poll_s = make_session, poll_s
        self.snapshots: dict[str, dict[str, Any] | None] = {}
        self._followers: dict[str, int] = {}
        self._tick = anyio.Event()
        self._polling = False
        self.polls = 0  # queries run by the shared poll (for tests and figures)

    async def _poll(self) -> None:
        try:
            while self._followers:
                await anyio.sleep(self.poll_s)
                ids = sorted(self._followers)
                if not ids:
                    break
                found = await run_in_threadpool(_load, self.make_session, ids)
                self.polls += 1
                for job_id in ids:
                    self.snapshots[job_id] = found.get(job_id)
                tick, self._tick = self._tick, anyio.Event()
                tick.set()
        finally:
            self._polling = False

    async def follow(self, job_id: str, wait_s: float) -> AsyncIterator[dict[str, Any] | None]:
        """The job's snapshot now, then after every poll or wait_s (None: the job is gone)."""
        self._followers[job_id] = self._followers.get(job_id, 0) + 1
        try:
            self.snapshots[job_id] = (await run_in_threadpool(_load, self.make_session, [job_id])).get(job_id)
            if not self._polling:
                self._polling = True
                asyncio.get_running_loop().create_task(self._poll())
            while True:
                yield self.snapshots.get(job_id)
                tick = self._tick
                with anyio.move_on_after(wait_s):
                    await tick.wait()
        finally:
            self._followers[job_id] -= 1
            if not self._followers[job_id]:
                del self._followers[job_id]
                self.snapshots.pop(job_id, None)


def format_event(event: str, data: dict[str, Any], event_id: int | None = None) -> str:
    lines = [f"event: {event}"]
    if event_id is not None:
        lines.append(f"id: {event_id}")
    lines.append("data: " + json.dumps(data, separators=(",", ":")))
    return "\n".join(lines) + "\n\n"


async def job_events(
    watch: JobWatch,
    job_id: str,
    heartbeat_s: float = 15.0,
    on_change: Callable[[], None] | None = None,
) -> AsyncIterator[str]:
    """`progress` events (the job snapshot) whenever the row changes, `end` once it is final, `error` if
    the job disappears; keep-alive comments while nothing changes. The first event is sent at once.
    on_change runs before each event that tells of a change (the app drops its cached status read, so
    that a client that GETs the job after an event gets at least what the event told)."""
    last: dict[str, Any] | None = None
    n = 0
    last_sent = time.monotonic()
    yield f"retry: {int(max(watch.poll_s, 1.0) * 1000)}\n\n"
    async for snap in watch.follow(job_id, heartbeat_s):
        if snap is None:
            yield format_event("error", {"detail": f"job {job_id} not found"})
            return
        if snap != last:
            if on_change is not None and last is not None:
                on_change()
            n += 1
            yield format_event("progress", snap, n)
            last, last_sent = snap, time.monotonic()
            if snap["status"] in {s.value for s in TERMINAL_JOB_STATUSES}:
                end = {"id": job_id, "status": snap["status"], "outcome": snap["outcome"]}
                yield format_event("end", end, n + 1)
                return
        elif time.monotonic() - last_sent >= heartbeat_s:
            yield ": keep-alive\n\n"
            last_sent = time.monotonic()
