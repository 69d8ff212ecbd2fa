"""Server-sent events of a job's progress: the job row is polled, every change is sent, the stream ends
when the job reaches a final status."""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import anyio
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
        "attempt": job.attempt,
        "error": job.error,
        "timings": job.timings or {},
        "metrics": job.metrics or {},
        "outcome": (job.metrics or {}).get("outcome"),
        "started_at": job.started_at.isoformat() if job.started_at else None,
        "finished_at": job.finished_at.isoformat() if job.finished_at else None,
    }


def _load(make_session: sessionmaker[Session], job_id: str) -> dict[str, Any] | None:
    with make_session() as session:
        job = session.get(Job, job_id)
        return job_snapshot(job) if job is not None else None


def format_event(event: str, data: dict[str, Any], event_id: int | None = None) -> str:
    lines = [f"event: {event}"]
    if event_id is not None:
        lines.append(f"id: {event_id}")
    lines.append("data: " + json.dumps(data, separators=(",", ":")))
    return "\n".join(lines) + "\n\n"


async def job_events(
    make_session: sessionmaker[Session],
    job_id: str,
    poll_s: float = 0.5,
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
    yield f"retry: {int(max(poll_s, 1.0) * 1000)}\n\n"
    while True:
        snap = await run_in_threadpool(_load, make_session, job_id)
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
        await anyio.sleep(poll_s)
