"""A stage's log, kept by the server: the records its thread logs while the stage runs (the pipeline's
steps under the `midview` logger, and the stage's progress reports), appended to its stage run's row
(StageRun.log) in batches, so that `GET /jobs/{id}/log` and the dashboard show what the stage did, after
the fact and from any API process."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from sqlalchemy.orm import Session

from shared.db import crud

MAX_LOG_CHARS = 200_000  # of one task's share of a stage run's log; past it one line says it was cut
LOGGER = "midview"  # the pipeline's and the workers' loggers are below it
_FORMAT = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")


class StageLog(logging.Handler):
    """Collects the formatted records of one thread; `drain()` hands them over once (the caller appends
    them to the stage run in a session it already has open)."""

    def __init__(self, max_chars: int = MAX_LOG_CHARS):
        super().__init__(logging.INFO)
        self.setFormatter(_FORMAT)
        self.thread = threading.get_ident()
        self.max_chars = max_chars
        self._lines: list[str] = []
        self._chars = 0
        self._cut = False
        self._lock_lines = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        # a progress report adds its own line, whatever the logger's level (ProgressReporter)
        if record.thread == self.thread and not getattr(record, "progress_report", False):
            self.add(self.format(record))

    def add(self, line: str, stamp: bool = False) -> None:
        """Keep one line (until the share of the log is spent); stamp: prefix the time as records have."""
        if stamp:
            line = f"{time.strftime('%H:%M:%S')} {line}"
        with self._lock_lines:
            if self._chars + len(line) + 1 > self.max_chars:
                if not self._cut:
                    self._lines.append(f"... the log was cut at {self.max_chars} characters")
                    self._cut = True
                return
            self._lines.append(line)
            self._chars += len(line) + 1

    def drain(self) -> str:
        """The lines collected since the last drain, newline-terminated ('' when none)."""
        with self._lock_lines:
            lines, self._lines = self._lines, []
        return "".join(f"{line}\n" for line in lines)

    def write(self, session: Session, run_id: str | None) -> None:
        """Append what was collected to the stage run's log (in the caller's session)."""
        text = self.drain()
        if text and run_id is not None:
            crud.append_stage_log(session, run_id, text)


@contextmanager
def captured(flush: Callable[[StageLog], None]) -> Iterator[StageLog]:
    """Collect the `midview` records of this thread while the block runs; `flush(stage_log)` writes what
    is left at its end, whether it succeeds or fails (best effort: the database may be what failed)."""
    handler = StageLog()
    logger = logging.getLogger(LOGGER)
    logger.addHandler(handler)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        try:
            flush(handler)
        except Exception:
            logging.getLogger("midview.worker").exception("could not store the stage's log")
