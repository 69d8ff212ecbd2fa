"""Alembic environment: the URL comes from `-x url=...`, the caller (upgrade_database) or the settings."""

from __future__ import annotations

import logging.config
from typing import Any, Literal

import sqlalchemy as sa
from alembic import context

from shared.config import get_settings
from shared.db.models import Base, UTCDateTime

config = context.config
target_metadata = Base.metadata
MIGRATION_LOCK_ID = 0x6D69_6476  # pg_advisory_xact_lock key: one migrating process at a time


def _database_url() -> str:
    return (
        context.get_x_argument(as_dictionary=True).get("url")
        or config.attributes.get("url")
        or config.get_main_option("sqlalchemy.url")
        or get_settings().database_url
    )


def _render_item(type_: str, obj: Any, autogen_context: Any) -> str | Literal[False]:
    """Render the custom column types as plain SQLAlchemy ones in generated revisions."""
    if type_ == "type" and isinstance(obj, UTCDateTime):
        return "sa.DateTime(timezone=True)"
    return False


def _configure(**kwargs: Any) -> None:
    context.configure(
        target_metadata=target_metadata,
        render_item=_render_item,
        compare_type=True,
        **kwargs,
    )


def run_migrations_offline() -> None:
    """Emit SQL to stdout (`alembic upgrade head --sql`)."""
    _configure(url=_database_url(), literal_binds=True, dialect_opts={"paramstyle": "named"})
    with context.begin_transaction():
        context.run_migrations()


def _run_on(connection: sa.Connection) -> None:
    _configure(connection=connection, render_as_batch=connection.dialect.name == "sqlite")
    with context.begin_transaction():
        if connection.dialect.name == "postgresql":
            connection.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": MIGRATION_LOCK_ID})
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:  # shared.db.upgrade_database passes its own connection
        _run_on(connection)
        return
    if config.config_file_name is not None:  # the alembic command line
        logging.config.fileConfig(config.config_file_name, disable_existing_loggers=False)
    from shared.db.session import make_engine

    engine = make_engine(_database_url(), poolclass=sa.pool.NullPool)
    try:
        with engine.connect().execution_options(sqlite_immediate=True) as conn:
            _run_on(conn)
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
