"""`midview serve`: the service on one machine with embedded defaults: SQLite and a local storage folder
under DATA_DIR, jobs run by a thread of the API process (workers.embedded), no Redis, no Celery.

Register in cli/main.py:

    from cli import serve as serve_cli
    app.command("serve")(serve_cli.serve)

Every MIDVIEW_* setting still applies (e.g. MIDVIEW_DATABASE_URL, MIDVIEW_STORAGE=s3, or
MIDVIEW_DISPATCHER=celery to run only the API in front of Celery workers).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import typer

log = logging.getLogger("midview.cli.serve")


def bootstrap_key(settings: Any, api_key: str | None) -> str | None:
    """The key to print once: None when api_key was given (ensured at startup) or keys exist already;
    else a new key of tenant settings.bootstrap_tenant."""
    import sqlalchemy as sa

    from api.bootstrap import create_tenant_with_key
    from shared.db import crud
    from shared.db.models import ApiKey, Tenant
    from shared.db.session import make_engine, make_sessionmaker

    if api_key:
        return None
    engine = make_engine(settings.database_url)
    try:
        with make_sessionmaker(engine)() as s:
            if s.scalar(sa.select(sa.func.count()).select_from(ApiKey).where(ApiKey.revoked_at.is_(None))):
                return None
            tenant = s.scalar(sa.select(Tenant).where(Tenant.name == settings.bootstrap_tenant))
            if tenant is None:
                key = create_tenant_with_key(s, settings.bootstrap_tenant, pepper=settings.api_key_pepper)
            else:
                _, key = crud.create_api_key(s, tenant.id, "bootstrap", pepper=settings.api_key_pepper)
            s.commit()
            return key
    finally:
        engine.dispose()


def build_app(
    data_dir: Path | None = None, api_key: str | None = None, **overrides: Any
) -> tuple[Any, str | None]:
    """(app, new API key or None): settings, migrated database, bootstrap key, app with its dispatcher."""
    from api.config import ApiSettings
    from api.main import create_app
    from shared.db.session import upgrade_database
    from shared.dispatch import get_dispatcher

    kw: dict[str, Any] = dict(overrides)
    if data_dir is not None:
        kw["data_dir"] = data_dir
    if api_key:
        kw["bootstrap_api_key"] = api_key
    settings = ApiSettings(**kw)
    Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
    upgrade_database(settings.database_url)
    new_key = bootstrap_key(settings, api_key)
    app = create_app(settings)
    app.state.dispatcher = get_dispatcher(settings)  # started now: resumes jobs left unfinished
    return app, new_key


def serve(
    host: Annotated[str, typer.Option(help="Interface to listen on")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port")] = 8000,
    data_dir: Annotated[
        Path | None, typer.Option(help="Folder of the database, storage and job folders (MIDVIEW_DATA_DIR)")
    ] = None,
    api_key: Annotated[
        str | None, typer.Option(help="An API key (mv_...) to accept; default: create one if none exists")
    ] = None,
    open_browser: Annotated[bool, typer.Option("--open", help="Open the dashboard in a web browser")] = False,
) -> None:
    """Run the API, its web dashboard (/ui/) and the pipeline in one process (SQLite, local storage,
    embedded worker thread)."""
    import uvicorn

    from api.config import server_options

    app, new_key = build_app(data_dir, api_key)
    s = app.state.settings
    typer.echo(f"midview: database {s.database_url}, storage {s.storage}, dispatcher {s.dispatcher}")
    if new_key:
        typer.secho(f"API key (shown once, keep it): {new_key}", fg="green", bold=True)
        typer.echo(f'  curl -H "Authorization: Bearer {new_key}" http://{host}:{port}/projects')
    typer.echo(f"dashboard: http://{host}:{port}/ui/ (sign in with the API key)")
    if open_browser:
        import threading
        import webbrowser

        threading.Timer(1.5, webbrowser.open, [f"http://{host}:{port}/ui/"]).start()
    uvicorn.run(app, host=host, port=port, log_level=str(s.log_level).lower(), **server_options(s))
