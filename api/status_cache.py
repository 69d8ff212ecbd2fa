"""The job status read that clients poll (GET /jobs/{id}), answered from memory for a moment.

Clients and dashboards poll a running job's status, often many of them the same job. Each read costs a
thread, a pooled connection and two queries; `StatusCache` keeps the serialized answer of a job for
`ttl_s` seconds (settings.status_cache_s, half a second: the event stream's own poll period), so that a
flood of polls costs one read per job per ttl_s. Concurrent misses of one job share one read (single
flight), and an entry that just expired is served while one read refreshes it in the background (stale
while revalidate): a read in a worker thread competes for the GIL with a busy event loop and can take
100 ms, which every poller of the job would otherwise wait for. What the workers write shows up within
2 x ttl_s; what this process writes (cancel, rerun) drops the job's entry at once (`forget`). The entry
remembers the job's tenant: another tenant's key gets the 404 it would get from the database.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Entry:
    tenant_id: str
    body: bytes  # the JSON answer


class StatusCache:
    """job id -> Entry for ttl_s seconds (at most max_size jobs); ttl_s 0 turns it off."""

    def __init__(self, ttl_s: float, max_size: int = 10_000, clock=time.monotonic) -> None:
        self.ttl_s, self.max_size, self.clock = ttl_s, max_size, clock
        self._items: OrderedDict[str, tuple[float, Entry]] = OrderedDict()
        self._pending: dict[str, asyncio.Future[Entry | None]] = {}  # forget() drops a job's read

    async def get(
        self, job_id: str, tenant_id: str, load: Callable[[], Awaitable[Entry | None]]
    ) -> Entry | None:
        """The job's entry when it is tenant_id's (None: no such job of theirs); load() reads the job
        whoever's it is (its entry names its tenant). Fresh: from memory.
        Expired less than ttl_s ago: from memory too, while one load() in the background refreshes it
        (stale while revalidate: under a flood of polls nobody waits on the database). Older or absent:
        from load(), one load at a time per job, the others waiting for it."""
        if self.ttl_s <= 0:
            entry = await load()
            return entry if entry is not None and entry.tenant_id == tenant_id else None
        now = self.clock()
        item = self._items.get(job_id)
        if item is not None and item[1].tenant_id != tenant_id:
            return None  # another tenant's job: no load on their behalf
        if item is not None and item[0] > now:
            return item[1]
        pending = self._pending.get(job_id)
        if item is not None and item[0] + self.ttl_s > now:
            if pending is None:
                self._start(job_id, load)
            return item[1]
        if pending is None:
            pending = self._start(job_id, load)
        entry = await asyncio.shield(pending)
        return entry if entry is not None and entry.tenant_id == tenant_id else None

    def _start(
        self, job_id: str, load: Callable[[], Awaitable[Entry | None]]
    ) -> asyncio.Future[Entry | None]:
        """Run load() as a task that stores its entry (or drops the job's: None) when done."""

        async def run() -> Entry | None:
            try:
                entry = await load()
            finally:
                current = self._pending.get(job_id) is task  # not when forget() dropped it meanwhile
                if current:
                    del self._pending[job_id]
            if not current:
                return entry  # this read may predate what made the job forgotten: not stored
            if entry is None:  # unknown ids are not remembered: a flood of them cannot fill the cache
                self._items.pop(job_id, None)
                return None
            self._items[job_id] = (self.clock() + self.ttl_s, entry)
            self._items.move_to_end(job_id)
            while len(self._items) > self.max_size:
                self._items.popitem(last=False)
            return entry

        task = asyncio.ensure_future(run())
        task.add_done_callback(lambda t: t.cancelled() or t.exception())  # retrieved: no warning
        self._pending[job_id] = task
        return task

    def forget(self, job_id: str) -> None:
        """Drop the job's entry; a read already under way will not store its (maybe older) answer."""
        self._items.pop(job_id, None)
        self._pending.pop(job_id, None)
