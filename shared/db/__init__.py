"""Service state in SQL (PostgreSQL in production, SQLite embedded): models, sessions, migrations, CRUD."""

from __future__ import annotations

from shared.db.models import Base, JobStatus, StageStatus
from shared.db.session import (
    current_revision,
    downgrade_database,
    get_engine,
    get_session,
    make_engine,
    make_sessionmaker,
    session_scope,
    upgrade_database,
)

__all__ = [
    "Base",
    "JobStatus",
    "StageStatus",
    "current_revision",
    "downgrade_database",
    "get_engine",
    "get_session",
    "make_engine",
    "make_sessionmaker",
    "session_scope",
    "upgrade_database",
]
