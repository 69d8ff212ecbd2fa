"""workers/stagelog.py: a stage's log is its own thread's `midview` records, bounded, flushed at its end."""

from __future__ import annotations

import logging
import threading

import pytest

from workers.stagelog import StageLog, captured


@pytest.fixture
def info_level():
    logger = logging.getLogger("midview")
    level = logger.level
    logger.setLevel(logging.INFO)
    yield
    logger.setLevel(level)


def test_a_stage_log_keeps_its_threads_records_and_is_flushed_when_the_stage_fails(info_level):
    flushed: list[str] = []
    log = logging.getLogger("midview.sfm")
    with pytest.raises(RuntimeError), captured(lambda h: flushed.append(h.drain())) as stage_log:
        log.info("20 of %d registered", 20)
        logging.getLogger("other").warning("not the pipeline's")
        other = threading.Thread(target=lambda: log.info("another job's thread"))
        other.start()
        other.join()
        log.info("a progress line", extra={"progress_report": True})  # the reporter adds its own
        stage_log.add("aerial_sfm  50% matching", stamp=True)
        raise RuntimeError("the stage failed")
    assert len(flushed) == 1
    lines = flushed[0].splitlines()
    assert len(lines) == 2, lines
    assert lines[0].endswith("INFO midview.sfm: 20 of 20 registered")
    assert lines[1].endswith(" aerial_sfm  50% matching") and lines[1][2] == ":"  # HH:MM:SS first
    assert stage_log not in logging.getLogger("midview").handlers  # detached


def test_a_stage_log_is_cut_once_at_its_size():
    stage_log = StageLog(max_chars=50)
    for i in range(10):
        stage_log.add(f"line {i:02d} of the stage")
    text = stage_log.drain()
    assert text.splitlines() == [
        "line 00 of the stage",
        "line 01 of the stage",
        "... the log was cut at 50 characters",
    ]
    assert stage_log.drain() == ""
