"""What the Celery workers offer: each worker node advertises its device and queues in Redis, and the API
picks a job's profile (services.pipeline.PROFILES) from them when a request names none.

A node's main process writes `midview:worker:<hostname>` = {"device": "cuda" | "cpu", "queues": [...]}
every OFFER_EVERY_S with a TTL of OFFER_TTL_S (a node that died drops out within it) and deletes it on
shutdown. The device is probed in a child process, so that the node's main process never initialises
CUDA before it forks its pool.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import threading
from collections.abc import Iterable
from typing import Any

log = logging.getLogger("midview.workers.offer")

OFFER_PREFIX = "midview:worker:"
OFFER_EVERY_S = 20.0
OFFER_TTL_S = 60.0
PROFILE_QUEUE = "gpu"  # the queue of the 3DGS training: its workers' device decides the profile
PROBE = (
    "import torch\n"
    "from services.splat.backend import gsplat_available\n"
    "print('cuda' if torch.cuda.is_available() and gsplat_available() else 'cpu')\n"
)


def offer_key(hostname: str) -> str:
    return f"{OFFER_PREFIX}{hostname}"


def probe_device(timeout_s: float = 120.0) -> str:
    """ "cuda" when this machine trains 3DGS with gsplat on a GPU, else "cpu" (in a child process)."""
    try:
        out = subprocess.run(
            [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=timeout_s, check=True
        )
    except (subprocess.SubprocessError, OSError) as e:
        log.warning("could not probe the device (%s): offering cpu", e)
        return "cpu"
    return "cuda" if out.stdout.strip().endswith("cuda") else "cpu"


def profile_of(offers: Iterable[dict[str, Any]]) -> str:
    """The profile the workers offer: gpu when a worker of the 3DGS queue has a CUDA device, else cpu."""
    gpu = any(o.get("device") == "cuda" and PROFILE_QUEUE in (o.get("queues") or []) for o in offers)
    return "gpu" if gpu else "cpu"


def read_offers(redis: Any) -> list[dict[str, Any]]:
    """The offers of the live worker nodes."""
    keys = list(redis.scan_iter(match=f"{OFFER_PREFIX}*", count=200))
    offers = []
    for raw in redis.mget(keys) if keys else []:
        try:
            offers.append(json.loads(raw))
        except (TypeError, ValueError):
            continue
    return offers


class Advertiser:
    """A daemon thread of a worker node's main process writing its offer until stop()."""

    def __init__(self, redis: Any, hostname: str, queues: list[str], device: str | None = None):
        self.redis, self.hostname, self.queues = redis, hostname, sorted(queues)
        self.device = device
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="midview-offer", daemon=True)

    def start(self) -> Advertiser:
        self._thread.start()
        return self

    def _write(self) -> None:
        offer = {"device": self.device, "queues": self.queues, "hostname": self.hostname}
        self.redis.set(offer_key(self.hostname), json.dumps(offer), ex=int(OFFER_TTL_S))

    def _loop(self) -> None:
        if self.device is None:
            self.device = probe_device()
        log.info("worker %s offers %s on queues %s", self.hostname, self.device, ",".join(self.queues))
        while not self._stop.is_set():
            try:
                self._write()
            except Exception as e:  # the broker is away: try again at the next beat
                log.warning("worker %s: could not write its offer: %s", self.hostname, e)
            self._stop.wait(OFFER_EVERY_S)

    def stop(self) -> None:
        self._stop.set()
        try:
            self.redis.delete(offer_key(self.hostname))
        except Exception as e:
            log.warning("worker %s: could not withdraw its offer: %s", self.hostname, e)
