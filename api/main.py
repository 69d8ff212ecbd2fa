"""The FastAPI application factory.

Run it with `uvicorn --factory api.main:create_app` (settings from MIDVIEW_* variables), or build an
app on given settings with `create_app(settings)` (tests, the embedded service).
"""

from __future__ import annotations

import asyncio
import gc
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from api.auth import KeyCache
from api.bootstrap import ensure_api_key
from api.config import ApiSettings
from api.errors import install_error_handlers
from api.events import JobWatch
from api.gcwatch import GcWatch
from api.middleware import (
    BodyLimitMiddleware,
    KeyConcurrencyLimit,
    QueryCredentialsMiddleware,
    RedactCredentials,
    RequestLogMiddleware,
    SecurityHeadersMiddleware,
    dashboard_headers,
    inline_script_hashes,
    route_limits,
)
from api.ratelimit import make_rate_limiter
from api.routes import ROUTERS
from api.routes.ui import UI_DIR, mount_ui
from api.status_cache import StatusCache
from api.verify import Verifier
from shared.config import Settings
from shared.db.session import make_engine, make_sessionmaker, upgrade_database
from shared.storage import get_storage

log = logging.getLogger("midview.api")

DESCRIPTION = """Registers aerial (UAV) images with ground images through rendered intermediate views.

Authenticate with an API key: `Authorization: Bearer mv_...`. Image names are `SET/FILE`
(`aerial/A0001.jpg`, `ground/G0001.jpg`); errors are JSON `{"detail": ...}`.
"""


def _startup(app: FastAPI) -> None:
    settings: ApiSettings = app.state.settings
    if settings.migrate_on_startup:
        upgrade_database(settings.database_url)
    if settings.bootstrap_api_key:
        with app.state.sessionmaker() as session:
            ensure_api_key(
                session, settings.bootstrap_tenant, settings.bootstrap_api_key, settings.api_key_pepper
            )
            session.commit()


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    await run_in_threadpool(_startup, app)
    # the modules, the app and its routes (about 160k objects) never become garbage: out of the
    # collector's sight, a full collection takes microseconds instead of ~100 ms, which every request
    # in flight would wait for (the tail of the status read's latency under load)
    gc.collect()
    gc.freeze()
    watch = GcWatch().install()
    sweeper = asyncio.create_task(_sweep_uploads(app))
    try:
        yield
    finally:
        sweeper.cancel()
        watch.remove()
        app.state.verifier.close()
        close = getattr(app.state.dispatcher, "close", None)
        if callable(close):
            close()
        app.state.engine.dispose()


async def _sweep_uploads(app: FastAPI) -> None:
    """Check again, now and every verify_sweep_s, the uploads left verifying, and expire those left open
    too long (api/verify.py)."""
    while True:
        try:
            await run_in_threadpool(app.state.verifier.sweep)
            await run_in_threadpool(app.state.verifier.expire)
        except Exception:  # the database may be away for a while: the next sweep tries again
            log.exception("upload verification sweep failed")
        await asyncio.sleep(app.state.settings.verify_sweep_s)


def body_limits(settings: ApiSettings):
    """Request body limits per route: image uploads, parts of resumable uploads, POS files; JSON else."""
    project = r"/projects/[^/]+"
    return route_limits(
        [
            ("POST", project + "/images", settings.max_request_bytes),
            ("PUT", project + r"/uploads/[^/]+/parts/\d+", 2 * settings.upload_part_size),
            ("POST", project + "/pos", settings.max_pos_bytes + 1024 * 1024),
        ],
        settings.max_json_bytes,
    )


def create_app(settings: Settings | None = None) -> FastAPI:
    """An app on its own engine, storage and (lazily created) dispatcher, all kept in app.state."""
    if settings is None:
        settings = ApiSettings()
    elif not isinstance(settings, ApiSettings):
        settings = ApiSettings(**settings.model_dump())
    app = FastAPI(
        title="midview",
        version="0.1.0",
        description=DESCRIPTION,
        lifespan=_lifespan,
    )
    app.state.settings = settings
    pool = (
        {}
        if settings.database_url.startswith("sqlite")
        else {"pool_size": settings.db_pool_size, "max_overflow": settings.db_pool_size}
    )
    app.state.engine = make_engine(settings.database_url, **pool)
    app.state.db_limiter = anyio.CapacityLimiter(settings.db_pool_size)
    app.state.sessionmaker = make_sessionmaker(app.state.engine)
    # sessions of requests that write: BEGIN IMMEDIATE on SQLite (api.deps.get_db), plain elsewhere
    app.state.write_sessionmaker = make_sessionmaker(
        app.state.engine.execution_options(sqlite_immediate=True)
    )
    app.state.storage = get_storage(settings)
    app.state.dispatcher = None  # created on first use (api.deps.get_dispatcher)
    app.state.rate_limiter = make_rate_limiter(settings)
    app.state.key_cache = KeyCache(settings.auth_cache_s)
    app.state.status_cache = StatusCache(settings.status_cache_s)
    app.state.job_watch = JobWatch(app.state.sessionmaker, settings.events_poll_s)
    app.state.verifier = Verifier(
        app.state.write_sessionmaker,
        app.state.sessionmaker,
        app.state.storage,
        settings.upload_tmp_dir,
        settings.verify_workers,
        max_pixels=settings.max_image_pixels,
        expiry_s=settings.upload_expiry_h * 3600.0,
    )
    app.add_middleware(
        BodyLimitMiddleware, limit_for=body_limits(settings), read_timeout_s=settings.body_read_timeout_s
    )
    app.add_middleware(KeyConcurrencyLimit, limit=settings.max_concurrent_per_key)
    app.add_middleware(QueryCredentialsMiddleware)
    app.add_middleware(
        SecurityHeadersMiddleware,
        prefix="/ui",
        headers=dashboard_headers(inline_script_hashes((UI_DIR / "index.html").read_text())),
    )
    app.add_middleware(RequestLogMiddleware)
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactCredentials) for f in access.filters):
        access.addFilter(RedactCredentials())
    install_error_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    mount_ui(app)
    log.debug("app created: database %s, storage %r", app.state.engine.url, app.state.storage)
    return app
