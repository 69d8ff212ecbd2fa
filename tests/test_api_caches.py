"""The API's in-process caches that keep the status read cheap (api.status_cache, api.auth) and the
batched Redis rate limiter (api.ratelimit): their semantics, on a controlled clock."""

from __future__ import annotations

import asyncio

from api.auth import Caller, KeyCache
from api.status_cache import Entry, StatusCache


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_status_cache_fresh_stale_and_expired():
    clock = Clock()
    cache = StatusCache(0.5, clock=clock)
    loads: list[str] = []

    def loader(body: str, tenant: str = "t1"):
        async def load() -> Entry | None:
            loads.append(body)
            await asyncio.sleep(0.01)
            return Entry(tenant, body.encode())

        return load

    async def scenario() -> None:
        first = await cache.get("j", "t1", loader("v1"))
        assert first.body == b"v1" and loads == ["v1"]
        # fresh: from memory
        clock.t += 0.4
        assert (await cache.get("j", "t1", loader("v2"))).body == b"v1" and loads == ["v1"]
        # expired less than ttl ago: the stale answer at once, one refresh in the background
        clock.t += 0.2
        stale = await asyncio.gather(*(cache.get("j", "t1", loader("v2")) for _ in range(5)))
        assert {e.body for e in stale} == {b"v1"}
        await asyncio.sleep(0.05)
        assert loads == ["v1", "v2"]
        assert (await cache.get("j", "t1", loader("v3"))).body == b"v2"
        # expired long ago: wait for the database; concurrent misses share one load
        clock.t += 5
        got = await asyncio.gather(*(cache.get("j", "t1", loader("v4")) for _ in range(5)))
        assert {e.body for e in got} == {b"v4"} and loads == ["v1", "v2", "v4"]
        # another tenant's job: None, from memory or not; no load on their behalf
        assert await cache.get("j", "t2", loader("v5")) is None and loads[-1] == "v4"
        clock.t += 5
        assert await cache.get("j", "t2", loader("v5")) is None and loads[-1] == "v4"  # even expired
        assert (await cache.get("j", "t1", loader("v6"))).body == b"v6"
        cache.forget("j")  # not in memory: a miss loads whoever's job it is, and answers by its tenant
        assert await cache.get("j", "t2", loader("v7")) is None and loads[-1] == "v7"
        assert (await cache.get("j", "t1", loader("v8"))).body == b"v7"

        # unknown jobs are not remembered; forget drops an entry at once
        async def missing() -> None:
            return None

        assert await cache.get("nope", "t1", missing) is None and "nope" not in cache._items
        cache.forget("j")
        assert (await cache.get("j", "t1", loader("v9"))).body == b"v9"

    asyncio.run(scenario())


def test_status_cache_off_still_checks_the_tenant():
    cache = StatusCache(0)

    async def load() -> Entry:
        return Entry("t1", b"{}")

    assert asyncio.run(cache.get("j", "t2", load)) is None
    assert asyncio.run(cache.get("j", "t1", load)).body == b"{}"


def test_key_cache_expires_and_forgets():
    clock = Clock()
    cache = KeyCache(5.0, max_size=2, clock=clock)
    a, b, c = (Caller(f"t{i}", "n", f"k{i}", "mv_x") for i in range(3))
    cache.put("ha", a)
    assert cache.get("ha") is a
    clock.t += 5.01
    assert cache.get("ha") is None
    cache.put("ha", a), cache.put("hb", b), cache.put("hc", c)  # at most 2: the oldest goes
    assert cache.get("ha") is None and cache.get("hc") is c
    cache.forget("k2")
    assert cache.get("hc") is None and cache.get("hb") is b
    assert KeyCache(0).get("x") is None


def test_batched_redis_limiter_is_exact_for_one_process_and_shared(redis_url):
    """ahit counts locally and adds to Redis in batches, but within a batch of the limit at every hit:
    one process gets exactly `limit` requests a window; two share the window's count."""
    import uuid

    from api.ratelimit import RedisRateLimiter

    prefix = f"midview:test-rate-{uuid.uuid4().hex[:6]}:"
    key = "k"

    async def hits(limiter: RedisRateLimiter, n: int) -> list[float | None]:
        return [await limiter.ahit(key) for _ in range(n)]

    one = RedisRateLimiter(redis_url, limit=100, window_s=60.0, prefix=prefix)
    got = asyncio.run(hits(one, 120))
    assert all(w is None for w in got[:100]) and all(w is not None and w > 0 for w in got[100:])
    other = RedisRateLimiter(redis_url, limit=100, window_s=60.0, prefix=prefix)  # another API process
    assert all(w is not None for w in asyncio.run(hits(other, 3)))


def test_batched_redis_limiter_sends_one_sync_at_a_time(redis_url):
    """Hits that come while a key's count is on its way to Redis wait for the next sync instead of
    each sending their own (50 concurrent requests once sent 50 pipelines at every sync: the tail of
    the status read's latency under load); the count in Redis still gets every hit."""
    import uuid

    import redis

    from api.ratelimit import RedisRateLimiter

    prefix = f"midview:test-rate-{uuid.uuid4().hex[:6]}:"
    limiter = RedisRateLimiter(redis_url, limit=10**6, window_s=60.0, prefix=prefix)
    pipelines = []

    async def scenario() -> None:
        client = limiter._async_client()
        real = client.pipeline

        def counted(*args, **kwargs):
            pipelines.append(1)
            return real(*args, **kwargs)

        client.pipeline = counted
        got = await asyncio.gather(*(limiter.ahit("k") for _ in range(50)))
        assert all(w is None for w in got)
        assert len(pipelines) == 1, len(pipelines)  # the first hit syncs, the 49 others count locally
        limiter._tallies["k"].synced_at = 0.0  # the sync interval over: the next hit sends the 49
        await limiter.ahit("k")
        assert len(pipelines) == 2

    asyncio.run(scenario())
    name = next(iter(redis.Redis.from_url(redis_url).scan_iter(f"{prefix}*")))
    assert int(redis.Redis.from_url(redis_url).get(name)) == 51


def test_key_cache_resolves_one_lookup_at_a_time():
    clock = Clock()
    cache = KeyCache(5.0, clock=clock)
    a = Caller("t1", "n", "k1", "mv_x")
    lookups: list[str] = []

    def lookup(answer):
        async def run():
            lookups.append("db")
            await asyncio.sleep(0.01)
            return answer

        return run

    async def scenario() -> None:
        got = await asyncio.gather(*(cache.resolve("h", lookup((a, None))) for _ in range(20)))
        assert all(c is a for c, _ in got) and lookups == ["db"]  # 20 requests, one lookup
        clock.t += 5.01  # expired: the first request looks the key up, the others get the old entry
        first = asyncio.ensure_future(cache.resolve("h", lookup((None, "API key revoked"))))
        await asyncio.sleep(0)
        assert (await cache.resolve("h", lookup((a, None))))[0] is a
        assert await first == (None, "API key revoked") and len(lookups) == 2  # revoked: forgotten
        assert (await cache.resolve("h", lookup((None, "API key revoked"))))[0] is None

    asyncio.run(scenario())


def test_status_cache_forget_wins_over_a_read_under_way():
    """A read that started before forget() (an event told of a change) does not store its answer: the
    next read goes to the database."""
    cache = StatusCache(0.5)

    async def scenario() -> None:
        gate = asyncio.Event()

        async def slow() -> Entry:
            await gate.wait()
            return Entry("t1", b"old")

        async def fresh() -> Entry:
            return Entry("t1", b"new")

        first = asyncio.ensure_future(cache.get("j", "t1", slow))
        await asyncio.sleep(0)
        cache.forget("j")  # the job changed while the read was under way
        gate.set()
        assert (await first).body == b"old"  # its own caller gets what it read
        assert (await cache.get("j", "t1", fresh)).body == b"new"  # not served from memory

    asyncio.run(scenario())
