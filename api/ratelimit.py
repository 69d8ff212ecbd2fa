"""Per-API-key request rate limits: a token bucket in the process (embedded service), or a window
counter in Redis shared by every API process (the distributed service).

`hit(key)` takes one request from the key's allowance and returns None, or the seconds to wait
(the 429's Retry-After) when the allowance is spent.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
import weakref
from dataclasses import dataclass
from typing import Any, Protocol

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


@dataclass
class _Tally:
    """One key's window as this process knows it (RedisRateLimiter.ahit)."""

    window: int
    shared: int = 0  # the window's count in Redis at the last sync
    pending: int = 0  # hits of this process not yet added to Redis
    synced_at: float = 0.0
    syncing: bool = False  # an INCRBY of this key is on its way to Redis


class RedisRateLimiter:
    """A fixed window of `window_s` seconds per key in Redis (INCR + EXPIRE), `limit` requests each;
    fails open (no limit, a warning in the log) while Redis does not answer. Async callers use ahit()."""

    BATCH = 32
    SYNC_S = 0.25

    def __init__(self, url: str, limit: int, window_s: float = 60.0, prefix: str = "midview:rate:") -> None:
        import redis

        self.url = url
        self.client = redis.Redis.from_url(url, socket_connect_timeout=1.0, socket_timeout=1.0)
        self._async_clients: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Any] = (
            weakref.WeakKeyDictionary()
        )
        self.limit, self.window_s, self.prefix = limit, window_s, prefix
        self._tallies: dict[str, _Tally] = {}

    async def ahit(self, key: str) -> float | None:
        """hit() for async callers, in batches: this process counts a key's hits itself and adds them
        to Redis (INCRBY, on the running loop's redis.asyncio client) every SYNC_S seconds or BATCH
        hits, and at every hit once the window's count comes within BATCH of the limit, so the limit
        holds exactly for one process and within a batch per process for several. A status poll costs
        no Redis round trip most of the time."""
        import redis

        now = time.time()
        name, window = self._name(key, now)
        tally = self._tallies.get(key)
        if tally is None or tally.window != window:
            tally = self._tallies[key] = _Tally(window)
        tally.pending += 1
        near = tally.shared + tally.pending + self.BATCH >= self.limit
        if not near and (
            tally.syncing or (tally.pending < self.BATCH and now - tally.synced_at < self.SYNC_S)
        ):  # one sync at a time: the hits that come while one is on its way go with the next
            return None
        n, tally.pending, tally.syncing = tally.pending, 0, True
        try:
            async with self._async_client().pipeline() as pipe:
                pipe.incrby(name, n)
                pipe.expire(name, int(self.window_s * 2))
                count = int((await pipe.execute())[0])
        except (redis.RedisError, OSError) as e:
            log.warning("rate limit not applied: Redis does not answer (%s)", e)
            return None
        finally:
            tally.syncing = False
        tally.shared, tally.synced_at = max(tally.shared, count), now
        return self._wait(count + tally.pending, window, now)

    def _async_client(self) -> Any:
        loop = asyncio.get_running_loop()
        client = self._async_clients.get(loop)
        if client is None:
            import redis.asyncio

            client = redis.asyncio.Redis.from_url(self.url, socket_connect_timeout=1.0, socket_timeout=1.0)
            self._async_clients[loop] = client
        return client

    def _name(self, key: str, now: float) -> tuple[str, int]:
        window = math.floor(now / self.window_s)
        return f"{self.prefix}{key}:{window}", window

    def _wait(self, count: int, window: int, now: float) -> float | None:
        if count <= self.limit:
            return None
        return (window + 1) * self.window_s - now

    def hit(self, key: str) -> float | None:
        import redis

        now = time.time()
        name, window = self._name(key, now)
        try:
            pipe = self.client.pipeline()
            pipe.incr(name)
            pipe.expire(name, int(self.window_s * 2))
            count = int(pipe.execute()[0])
        except redis.RedisError as e:
            log.warning("rate limit not applied: Redis does not answer (%s)", e)
            return None
        return self._wait(count, window, now)


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
