"""Logging with the pipeline stage in every record (`stage` context), as text or JSON lines."""

from __future__ import annotations

import contextlib
import contextvars
import json
import logging
import time
from collections.abc import Iterator

_stage: contextvars.ContextVar[str] = contextvars.ContextVar("midview_stage", default="-")


class _StageFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        record.stage = _stage.get()
        return True


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return json.dumps(
            {
                "time": self.formatTime(record),
                "level": record.levelname,
                "logger": record.name,
                "stage": getattr(record, "stage", "-"),
                "message": record.getMessage(),
            }
        )


def setup_logging(level: str = "INFO", json_lines: bool = False) -> None:
    handler = logging.StreamHandler()
    handler.addFilter(_StageFilter())
    if json_lines:
        handler.setFormatter(_JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s [%(stage)s] %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)  # a line per plugin at import


@contextlib.contextmanager
def stage(name: str, logger: logging.Logger | None = None) -> Iterator[None]:
    """Run a block as pipeline stage `name`: its records carry the name; start and end are logged."""
    log = logger or logging.getLogger("midview")
    token = _stage.set(name)
    t0 = time.perf_counter()
    log.info("stage started")
    try:
        yield
    except BaseException:
        log.exception("stage failed after %.1f s", time.perf_counter() - t0)
        raise
    else:
        log.info("stage finished in %.1f s", time.perf_counter() - t0)
    finally:
        _stage.reset(token)
