"""Garbage-collector pauses of the API process: a pause stops every request in flight, so the long ones
are logged (`gc pause: generation 2, 84.1 ms, 1203 collected`) and counted, the tail of the latency
they make visible in the logs."""

from __future__ import annotations

import gc
import logging
import time
from typing import Any

log = logging.getLogger("midview.api.gc")


class GcWatch:
    """Times every collection through gc.callbacks; logs those over `threshold_ms`."""

    def __init__(self, threshold_ms: float = 20.0) -> None:
        self.threshold_ms = threshold_ms
        self.long_pauses = 0
        self.worst_ms = 0.0
        self._t0 = 0.0

    def __call__(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        ms = (time.perf_counter() - self._t0) * 1000
        self.worst_ms = max(self.worst_ms, ms)
        if ms >= self.threshold_ms:
            self.long_pauses += 1
            log.warning(
                "gc pause: generation %d, %.1f ms, %d collected", info["generation"], ms, info["collected"]
            )

    def install(self) -> GcWatch:
        if self not in gc.callbacks:
            gc.callbacks.append(self)
        return self

    def remove(self) -> None:
        if self in gc.callbacks:
            gc.callbacks.remove(self)
