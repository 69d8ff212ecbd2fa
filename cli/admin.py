"""`midview admin`: tenants, API keys and webhook secrets, on the database of MIDVIEW_DATABASE_URL (or
--database-url). Keys are shown once, when made; only their hashes are stored (HMAC with
MIDVIEW_API_KEY_PEPPER where set).

    midview admin tenant-create acme                 # the tenant and its first key
    midview admin tenants
    midview admin key-create acme --name ci
    midview admin keys acme
    midview admin key-revoke KEY_ID
    midview admin webhook-rotate WEBHOOK_ID          # a new signing secret, shown once
"""

from __future__ import annotations

from contextlib import contextmanager

import typer

app = typer.Typer(help="Tenants, API keys and webhook secrets (operators).", no_args_is_help=True)

DatabaseOption = typer.Option(None, "--database-url", help="SQLAlchemy URL (default: MIDVIEW_DATABASE_URL)")
JsonOption = typer.Option(False, "--json", help="print JSON")


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


@contextmanager
def _session(database_url: str | None):
    from sqlalchemy.exc import SQLAlchemyError

    from shared.config import get_settings
    from shared.db.session import make_engine, make_sessionmaker

    url = database_url or get_settings().database_url
    engine = make_engine(url)
    try:
        with make_sessionmaker(engine)() as session:
            yield session
            session.commit()
    except SQLAlchemyError as e:
        _fail(f"database {engine.url!r}: {type(e).__name__}: {str(e).splitlines()[0]}")
    finally:
        engine.dispose()


def _tenant(session, name_or_id: str):
    import sqlalchemy as sa

    from shared.db.models import Tenant

    t = session.scalar(sa.select(Tenant).where(sa.or_(Tenant.name == name_or_id, Tenant.id == name_or_id)))
    if t is None:
        _fail(f"no tenant {name_or_id!r}")
    return t


def _pepper() -> str:
    from shared.config import get_settings

    return get_settings().api_key_pepper


def _print(rows: list[dict], as_json: bool) -> None:
    import json

    if as_json:
        typer.echo(json.dumps(rows, indent=1, default=str))
        return
    for r in rows:
        typer.echo("  ".join(f"{k}={v}" for k, v in r.items()))


@app.command("tenant-create")
def tenant_create(
    name: str = typer.Argument(..., help="tenant name (unique)"),
    key_name: str = typer.Option("default", help="name of its first API key"),
    database_url: str = DatabaseOption,
    as_json: bool = JsonOption,
) -> None:
    """Create a tenant and its first API key; the key is printed once."""
    from shared.db import crud

    with _session(database_url) as s:
        try:
            tenant = crud.create_tenant(s, name)
        except crud.ConflictError as e:
            _fail(str(e))
        key, plaintext = crud.create_api_key(s, tenant.id, key_name, pepper=_pepper())
        row = {"tenant_id": tenant.id, "tenant": name, "key_id": key.id, "api_key": plaintext}
    _print([row], as_json)


@app.command("tenants")
def tenants(database_url: str = DatabaseOption, as_json: bool = JsonOption) -> None:
    """List the tenants with their number of active keys and projects."""
    import sqlalchemy as sa

    from shared.db.models import Tenant

    with _session(database_url) as s:
        rows = [
            {
                "tenant_id": t.id,
                "tenant": t.name,
                "active_keys": sum(k.revoked_at is None for k in t.api_keys),
                "projects": len(t.projects),
                "created_at": t.created_at.isoformat(),
            }
            for t in s.scalars(sa.select(Tenant).order_by(Tenant.created_at))
        ]
    _print(rows, as_json)


@app.command("key-create")
def key_create(
    tenant: str = typer.Argument(..., help="tenant name or id"),
    name: str = typer.Option("default", help="key name"),
    database_url: str = DatabaseOption,
    as_json: bool = JsonOption,
) -> None:
    """Create an API key for a tenant; the key is printed once."""
    from shared.db import crud

    with _session(database_url) as s:
        t = _tenant(s, tenant)
        key, plaintext = crud.create_api_key(s, t.id, name, pepper=_pepper())
        row = {"tenant": t.name, "key_id": key.id, "name": name, "api_key": plaintext}
    _print([row], as_json)


@app.command("keys")
def keys(
    tenant: str = typer.Argument(..., help="tenant name or id"),
    database_url: str = DatabaseOption,
    as_json: bool = JsonOption,
) -> None:
    """List a tenant's keys (id, name, prefix, revoked or not); never the keys themselves."""
    from shared.db import crud

    with _session(database_url) as s:
        t = _tenant(s, tenant)
        rows = [
            {
                "key_id": k.id,
                "name": k.name,
                "prefix": k.prefix,
                "created_at": k.created_at.isoformat(),
                "revoked_at": k.revoked_at.isoformat() if k.revoked_at else None,
            }
            for k in crud.list_api_keys(s, t.id)
        ]
    _print(rows, as_json)


@app.command("key-revoke")
def key_revoke(
    key_id: str = typer.Argument(..., help="key id (from `midview admin keys`)"),
    database_url: str = DatabaseOption,
    as_json: bool = JsonOption,
) -> None:
    """Revoke an API key: requests with it get 401 from now on, at the latest after MIDVIEW_AUTH_CACHE_S
    (5 s by default: how long each API process remembers a key that authenticated)."""
    from shared.db import crud

    with _session(database_url) as s:
        try:
            key = crud.revoke_api_key(s, key_id)
        except crud.NotFoundError as e:
            _fail(str(e))
        row = {"key_id": key.id, "prefix": key.prefix, "revoked_at": key.revoked_at.isoformat()}
    _print([row], as_json)


@app.command("webhook-rotate")
def webhook_rotate(
    webhook_id: str = typer.Argument(..., help="webhook id"),
    database_url: str = DatabaseOption,
    as_json: bool = JsonOption,
) -> None:
    """Give a webhook a new signing secret (printed once); deliveries are signed with it from now on."""
    from shared.db.models import Webhook
    from shared.webhooks import new_secret

    with _session(database_url) as s:
        hook = s.get(Webhook, webhook_id)
        if hook is None:
            _fail(f"no webhook {webhook_id!r}")
        hook.secret = new_secret()
        row = {"webhook_id": hook.id, "url": hook.url, "secret": hook.secret}
    _print([row], as_json)
