"""Per-API-key request rate limits: a token bucket in the process (embedded service), or a window
counter in Redis shared by every API process (the distributed service).

`hit(key)` takes one request from the key's allowance and returns None, or the seconds to wait
(the 429's Retry-After) when the allowance is spent.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Protocol

log = logging.getLogger("midview.api.ratelimit")


class RateLimiter(Protocol):
    def hit(self, key: str) -> float | None: ...


class NoLimit:
    def hit(self, key: str) -> float | None:
        return None


class MemoryRateLimiter:
    """Token buckets in this process: `per_minute` requests a minute on average, `burst` at once."""

    def __init__(self, per_minute: int, burst: int, clock=time.monotonic) -> None:
        self.rate = per_minute / 60.0
        self.burst = float(max(burst, 1))
        self.clock = clock
        self._buckets: dict[str, tuple[float, float]] = {}  # key -> (tokens, time)
        self._lock = threading.Lock()

    def hit(self, key: str) -> float | None:
        now = self.clock()
        with self._lock:
            tokens, last = self._buckets.get(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - last) * self.rate)
            if tokens >= 1.0:
                self._buckets[key] = (tokens - 1.0, now)
                return None
            self._buckets[key] = (tokens, now)
            return (1.0 - tokens) / self.rate


class RedisRateLimiter:
    """A fixed window of `window_s` seconds per key in Redis (INCR + EXPIRE), `limit` requests each;
    fails open (no limit, a warning in the log) while Redis does not answer."""

    def __init__(self, url: str, limit: int, window_s: float = 60.0, prefix: str = "midview:rate:") -> None:
        import redis

        self.client = redis.Redis.from_url(url, socket_connect_timeout=1.0, socket_timeout=1.0)
        self.limit, self.window_s, self.prefix = limit, window_s, prefix

    def hit(self, key: str) -> float | None:
        import redis

        now = time.time()
        window = math.floor(now / self.window_s)
        name = f"{self.prefix}{key}:{window}"
        try:
            pipe = self.client.pipeline()
            pipe.incr(name)
            pipe.expire(name, int(self.window_s * 2))
            count = int(pipe.execute()[0])
        except redis.RedisError as e:
            log.warning("rate limit not applied: Redis does not answer (%s)", e)
            return None
        if count <= self.limit:
            return None
        return (window + 1) * self.window_s - now


def make_rate_limiter(settings) -> RateLimiter:
    """The limiter of an API's settings: off (rate_limit_per_minute 0), in Redis (the broker's, with the
    Celery dispatcher, or rate_limit_backend "redis"), else in this process."""
    per_minute = settings.rate_limit_per_minute
    if per_minute <= 0:
        return NoLimit()
    backend = settings.rate_limit_backend
    if backend == "auto":
        shared = settings.dispatcher == "celery" and settings.broker_url.startswith("redis")
        backend = "redis" if shared else "memory"
    if backend == "redis":
        return RedisRateLimiter(settings.broker_url, per_minute)
    return MemoryRateLimiter(per_minute, settings.rate_limit_burst)
