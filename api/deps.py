"""FastAPI dependencies: settings, database session, storage, dispatcher, and the authenticated tenant.

Everything comes from `app.state` (set by api.main.create_app), so that several apps with different
settings can live in one process (tests). Tests replace `get_dispatcher` with
`app.dependency_overrides`.
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import Callable, Iterator
from functools import partial
from typing import Annotated, Any, TypeVar

import anyio
from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from api.auth import Caller, lookup_key
from api.config import ApiSettings
from shared.db import crud
from shared.db.models import Job, Project
from shared.dispatch import Dispatcher, DispatcherError
from shared.dispatch import get_dispatcher as make_dispatcher
from shared.storage import Storage

T = TypeVar("T")
_bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer mv_...`")
_dispatcher_lock = threading.Lock()


async def run_db(request: Request, fn: Callable[..., T], *args: Any) -> T:
    """fn(*args) in a worker thread, at most db_pool_size at once per app (app.state.db_limiter): work
    that takes a pooled connection waits for a thread here, never for a connection in a thread."""
    return await anyio.to_thread.run_sync(partial(fn, *args), limiter=request.app.state.db_limiter)


async def get_settings(request: Request) -> ApiSettings:
    return request.app.state.settings


READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def get_db(request: Request) -> Iterator[Session]:
    """One session per request; routes commit what they keep, anything else is rolled back.

    On SQLite a request that may write (not GET, HEAD, OPTIONS) begins its transactions with BEGIN
    IMMEDIATE: it takes the write lock with its first statement and waits for it (busy_timeout). A
    deferred transaction that read (the API key) before writing could not take the lock once another
    connection (the embedded worker) had committed since: "database is locked" at once."""
    state = request.app.state
    maker = state.sessionmaker if request.method in READ_METHODS else state.write_sessionmaker
    with maker() as session:
        yield session


async def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_dispatcher(request: Request) -> Dispatcher:
    """The app's dispatcher, created on first use; 503 if it cannot be (e.g. Celery not installed)."""
    state = request.app.state
    if state.dispatcher is None:
        with _dispatcher_lock:
            if state.dispatcher is None:
                try:
                    state.dispatcher = make_dispatcher(state.settings)
                except DispatcherError as e:
                    raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"job dispatch: {e}") from e
    return state.dispatcher


SettingsDep = Annotated[ApiSettings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_db)]
StorageDep = Annotated[Storage, Depends(get_storage)]
DispatcherDep = Annotated[Dispatcher, Depends(get_dispatcher)]


def _unauthorized(reason: str, error: str = "invalid_token") -> HTTPException:
    challenge = f'Bearer realm="midview", error="{error}", error_description="{reason}"'
    return HTTPException(status.HTTP_401_UNAUTHORIZED, reason, headers={"WWW-Authenticate": challenge})


async def get_current_tenant(
    request: Request, _credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> Caller:
    """The tenant of the bearer API key; 401 with the reason when missing, malformed, unknown or revoked,
    429 with Retry-After when the key has spent its rate limit. A key seen lately comes from the app's
    KeyCache (api.auth): no database work on the event loop nor in the thread pool."""
    # yield to the event loop once: requests that need no I/O would otherwise run to completion as soon
    # as they are read, and under a flood the connections read first get served again and again while
    # others wait (a p99 of 300 ms at a p50 of 20 ms); after this, requests are served in arrival order
    await asyncio.sleep(0)
    header = request.headers.get("authorization")
    if not header:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing Authorization header (expected 'Bearer <API key>')",
            headers={"WWW-Authenticate": 'Bearer realm="midview"'},
        )
    scheme, _, token = header.partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        raise _unauthorized("malformed Authorization header (expected 'Bearer <API key>')", "invalid_request")
    state = request.app.state
    key_hash = crud.hash_api_key(token, state.settings.api_key_pepper)
    caller, reason = await state.key_cache.resolve(
        key_hash, lambda: run_db(request, lookup_key, state.sessionmaker, key_hash)
    )
    if caller is None:
        raise _unauthorized(reason or "invalid API key")
    limiter = state.rate_limiter
    ahit = getattr(limiter, "ahit", None)  # a limiter that waits on the network (Redis) has ahit
    wait = await ahit(caller.key_id) if ahit is not None else limiter.hit(caller.key_id)
    if wait is not None:
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            f"rate limit of {state.settings.rate_limit_per_minute} requests a minute for this API key "
            f"reached; retry in {math.ceil(wait)} s",
            headers={"Retry-After": str(max(1, math.ceil(wait)))},
        )
    request.state.tenant_id = caller.id  # for the request log
    request.state.api_key_prefix = caller.key_prefix
    return caller


TenantDep = Annotated[Caller, Depends(get_current_tenant)]


def get_project(
    project_id: Annotated[str, Path(description="Project id")], tenant: TenantDep, session: SessionDep
) -> Project:
    """The tenant's project; 404 when absent or another tenant's."""
    project = crud.get_project(session, project_id, tenant.id)
    if project is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"project {project_id} not found")
    return project


def get_job(
    job_id: Annotated[str, Path(description="Job id")], tenant: TenantDep, session: SessionDep
) -> Job:
    """The tenant's job; 404 when absent or another tenant's."""
    job = crud.get_job(session, job_id, tenant.id, with_stages=True)
    if job is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} not found")
    return job


ProjectDep = Annotated[Project, Depends(get_project)]
JobDep = Annotated[Job, Depends(get_job)]
