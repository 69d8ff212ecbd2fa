"""Engines, sessions and programmatic migrations."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from shared.config import get_settings

MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
ALEMBIC_INI = Path(__file__).resolve().parents[2] / "alembic.ini"


def _sqlite_connect(dbapi_conn: Any, _record: Any, wal: bool = False) -> None:
    # let SQLAlchemy, not pysqlite, begin transactions so that SAVEPOINTs nest properly
    dbapi_conn.isolation_level = None
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA foreign_keys=ON")  # ON DELETE CASCADE needs it
    cur.execute("PRAGMA busy_timeout=10000")  # API and workers share the file
    if wal:
        cur.execute("PRAGMA journal_mode=WAL")  # readers do not block the writer
    cur.close()


def _sqlite_begin(conn: sa.Connection) -> None:
    # execution option sqlite_immediate=True takes the write lock at once (writers then queue on
    # busy_timeout instead of failing with "database is locked" when a read lock cannot be upgraded)
    conn.exec_driver_sql(
        "BEGIN IMMEDIATE" if conn.get_execution_options().get("sqlite_immediate") else "BEGIN"
    )


def make_engine(url: str, **kwargs: Any) -> sa.Engine:
    """A new engine; for SQLite: create the folder of the file, enable foreign keys, WAL, savepoints."""
    u = make_url(url)
    is_file = bool(u.database) and u.database != ":memory:" and not str(u.database).startswith("file:")
    if u.get_backend_name() == "sqlite":
        if is_file:
            Path(str(u.database)).parent.mkdir(parents=True, exist_ok=True)
        kwargs.setdefault("connect_args", {}).setdefault("check_same_thread", False)
    else:
        kwargs.setdefault("pool_pre_ping", True)
    engine = sa.create_engine(url, **kwargs)
    if u.get_backend_name() == "sqlite":
        sa.event.listen(engine, "connect", lambda c, r: _sqlite_connect(c, r, wal=is_file))
        sa.event.listen(engine, "begin", _sqlite_begin)
    return engine


def begin_write(session: Session) -> None:
    """Before a session's first write on SQLite, make its transaction a writing one (BEGIN IMMEDIATE).

    A deferred SQLite transaction that has read cannot take the write lock once another connection has
    committed since (WAL snapshot): SQLite answers "database is locked" at once, busy_timeout does not
    help (the embedded worker commits progress while the API cancels a job). A transaction that has not
    flushed anything yet is committed (it only read) and begun again with BEGIN IMMEDIATE, which waits
    on busy_timeout for the lock; the caller reloads what it writes. Nothing to do on PostgreSQL (rows
    are locked FOR UPDATE) or when the transaction has written already (it holds the lock)."""
    if session.get_bind().dialect.name != "sqlite":
        return
    tx = session.get_transaction()
    if tx is not None and session.info.get("wrote_in") is tx:
        return
    if session.new or session.dirty or session.deleted:
        session.flush()  # pending writes take the lock now (or fail here, before anything is lost)
        return
    if tx is not None:
        session.commit()
    session.connection(execution_options={"sqlite_immediate": True})
    session.info["wrote_in"] = session.get_transaction()


@sa.event.listens_for(Session, "after_flush")
def _mark_writing(session: Session, _ctx: Any) -> None:
    session.info["wrote_in"] = session.get_transaction()


@lru_cache(maxsize=8)
def get_engine(url: str | None = None) -> sa.Engine:
    """The process-wide engine of a URL (default: settings.database_url)."""
    return make_engine(url or get_settings().database_url)


def make_sessionmaker(engine: sa.Engine) -> sessionmaker[Session]:
    """Sessions that keep their objects readable after commit."""
    return sessionmaker(bind=engine, expire_on_commit=False)


@contextmanager
def session_scope(engine: sa.Engine | None = None) -> Iterator[Session]:
    """A session that commits on success and rolls back on error (workers, CLI, tests)."""
    with make_sessionmaker(engine or get_engine())() as session:
        try:
            yield session
            session.commit()
        except BaseException:
            session.rollback()
            raise


def get_session() -> Iterator[Session]:
    """FastAPI dependency: one session per request; the route commits what it wants to keep."""
    with make_sessionmaker(get_engine())() as session:
        yield session


def alembic_config(url: str | None = None) -> Config:
    """The Alembic configuration of the repository, pointed at url (default: settings.database_url)."""
    cfg = Config(str(ALEMBIC_INI)) if ALEMBIC_INI.is_file() else Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.attributes["url"] = url or get_settings().database_url
    return cfg


def upgrade_database(url: str | None = None, revision: str = "head") -> None:
    """Apply the migrations up to revision (SQLite or PostgreSQL); creates the SQLite folder if needed."""
    _run_alembic(command.upgrade, url, revision)


def downgrade_database(url: str | None = None, revision: str = "base") -> None:
    """Revert the migrations down to revision (default: an empty database)."""
    _run_alembic(command.downgrade, url, revision)


def _run_alembic(fn: Any, url: str | None, revision: str) -> None:
    """Run an Alembic command in one transaction (PostgreSQL: under an advisory lock, see env.py)."""
    cfg = alembic_config(url)
    engine = make_engine(cfg.attributes["url"], poolclass=sa.pool.NullPool)
    try:
        with engine.execution_options(sqlite_immediate=True).begin() as conn:
            cfg.attributes["connection"] = conn
            fn(cfg, revision)
    finally:
        engine.dispose()


def current_revision(url: str | None = None) -> str | None:
    """The revision the database is at, or None when it has never been migrated."""
    from alembic.runtime.migration import MigrationContext

    engine = make_engine(url or get_settings().database_url, poolclass=sa.pool.NullPool)
    try:
        with engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()
    finally:
        engine.dispose()
