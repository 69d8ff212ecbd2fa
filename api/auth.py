"""API key authentication without a database round trip per request.

Every request names its API key; looking the key up in the database costs a connection checkout and a
query, and on a busy API those requests queue for the thread pool and the connection pool together.
`KeyCache` keeps the keys that authenticated for `ttl_s` seconds (settings.auth_cache_s) in this
process: a key revoked (`midview admin key-revoke`) stops working within ttl_s. Unknown or revoked keys
are not cached: each such request asks the database again.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from shared.db.models import ApiKey, Tenant


@dataclass(frozen=True)
class Caller:
    """The tenant an API key authenticates (`id` is the tenant's id, as routes use it) and the key."""

    id: str
    name: str
    key_id: str
    key_prefix: str


class KeyCache:
    """key hash -> Caller for ttl_s seconds, at most max_size keys (least recently used go first)."""

    def __init__(self, ttl_s: float, max_size: int = 10_000, clock=time.monotonic) -> None:
        self.ttl_s, self.max_size, self.clock = ttl_s, max_size, clock
        self._items: OrderedDict[str, tuple[float, Caller]] = OrderedDict()
        self._pending: dict[str, asyncio.Future[tuple[Caller | None, str | None]]] = {}
        self._lock = threading.Lock()

    def get(self, key_hash: str) -> Caller | None:
        with self._lock:
            item = self._items.get(key_hash)
            if item is None:
                return None
            if item[0] <= self.clock():
                return None  # kept for resolve() to serve while its lookup runs
            self._items.move_to_end(key_hash)
            return item[1]

    async def resolve(
        self, key_hash: str, lookup: Callable[[], Awaitable[tuple[Caller | None, str | None]]]
    ) -> tuple[Caller | None, str | None]:
        """(caller, None), or (None, why not): from memory while fresh, else from lookup(). One lookup
        per key at a time: requests that arrive while it runs get the expired entry if there is one
        (they would otherwise all wait for a thread and a connection at once, every ttl_s), or share
        the lookup's answer."""
        caller = self.get(key_hash)
        if caller is not None:
            return caller, None
        pending = self._pending.get(key_hash)
        if pending is not None:
            with self._lock:
                item = self._items.get(key_hash)
            if item is not None:
                return item[1], None
            return await asyncio.shield(pending)

        async def run() -> tuple[Caller | None, str | None]:
            try:
                found, reason = await lookup()
            finally:
                self._pending.pop(key_hash, None)
            if found is None:
                with self._lock:
                    self._items.pop(key_hash, None)
            else:
                self.put(key_hash, found)
            return found, reason

        task = asyncio.ensure_future(run())
        task.add_done_callback(lambda t: t.cancelled() or t.exception())
        self._pending[key_hash] = task
        return await asyncio.shield(task)

    def put(self, key_hash: str, caller: Caller) -> None:
        if self.ttl_s <= 0:
            return
        with self._lock:
            self._items[key_hash] = (self.clock() + self.ttl_s, caller)
            self._items.move_to_end(key_hash)
            while len(self._items) > self.max_size:
                self._items.popitem(last=False)

    def forget(self, key_id: str | None = None) -> None:
        """Drop a key (by its id), or every key."""
        with self._lock:
            if key_id is None:
                self._items.clear()
                return
            for h in [h for h, (_, c) in self._items.items() if c.key_id == key_id]:
                del self._items[h]


def lookup_key(maker: sessionmaker[Session], key_hash: str) -> tuple[Caller | None, str | None]:
    """(the caller, None) of a key hash, or (None, why not): unknown or revoked. One query, in a session
    of its own that is closed before the request goes on."""
    stmt = sa.select(ApiKey, Tenant).join(Tenant, ApiKey.tenant_id == Tenant.id)
    with maker() as session:
        row = session.execute(stmt.where(ApiKey.key_hash == key_hash)).first()
        if row is None:
            return None, "invalid API key"
        key, tenant = row
        if key.revoked_at is not None:
            return None, "API key revoked"
        return Caller(tenant.id, tenant.name, key.id, key.prefix), None
