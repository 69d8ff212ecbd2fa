"""Liveness and readiness probes (no authentication)."""

from __future__ import annotations

import logging
from collections.abc import Callable

import anyio
import sqlalchemy as sa
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

router = APIRouter(tags=["health"])
log = logging.getLogger("midview.api")

PROBE_PREFIX = "healthz/"


@router.get("/healthz", summary="Liveness: the process answers")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


def _check_db(request: Request) -> None:
    with request.app.state.sessionmaker() as session:
        session.execute(sa.text("SELECT 1"))


def _check_storage(request: Request) -> None:
    request.app.state.storage.list(PROBE_PREFIX)  # S3: fails on a missing bucket or bad credentials


def _check_broker(request: Request) -> None:
    """The Celery broker answers: a Redis PING (redis://, rediss://), else a kombu connection."""
    settings = request.app.state.settings
    url, timeout_s = settings.broker_url, settings.readyz_timeout_s
    if url.split(":", 1)[0] in ("redis", "rediss"):
        import redis

        client = redis.Redis.from_url(
            url, socket_connect_timeout=timeout_s, socket_timeout=timeout_s, retry=None
        )
        try:
            client.ping()
        finally:
            client.close()
        return
    from kombu import Connection

    with Connection(url, connect_timeout=timeout_s) as conn:
        conn.ensure_connection(max_retries=1)


def _checks(request: Request) -> dict[str, Callable[[Request], None]]:
    """What readiness needs: the database, the storage, and the broker when jobs go through Celery."""
    checks: dict[str, Callable[[Request], None]] = {"database": _check_db, "storage": _check_storage}
    if request.app.state.settings.dispatcher == "celery":
        checks["broker"] = _check_broker
    return checks


async def _probe(name: str, check: Callable[[Request], None], request: Request, timeout_s: float) -> str:
    """ "ok", or "failed" when the check failed or did not finish in time (its thread is abandoned). The
    reason goes to the log only: the probe is unauthenticated, and reasons name internal addresses."""
    try:
        with anyio.fail_after(timeout_s):
            await anyio.to_thread.run_sync(check, request, abandon_on_cancel=True)
    except TimeoutError:
        log.warning("readiness: %s gave no answer within %g s", name, timeout_s)
        return "failed"
    except Exception as e:  # any failure means not ready
        log.warning("readiness: %s failed: %s", name, f"{type(e).__name__}: {e}"[:300])
        return "failed"
    return "ok"


@router.get(
    "/readyz",
    summary="Readiness: the database, the object storage and (Celery dispatcher) the broker are reachable",
    responses={503: {"description": "A dependency is unreachable"}},
)
async def readyz(request: Request) -> JSONResponse:
    timeout_s = request.app.state.settings.readyz_timeout_s
    checks = {name: await _probe(name, check, request, timeout_s) for name, check in _checks(request).items()}
    ready = all(v == "ok" for v in checks.values())
    body = {"status": "ok" if ready else "unavailable", "checks": checks}
    return JSONResponse(body if ready else {"detail": body}, status_code=200 if ready else 503)
