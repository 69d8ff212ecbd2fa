"""The Celery application of the midview workers.

    celery -A workers.celery_app worker -Q gpu,cpu,reduce,control -c 1   # or: midview worker --queues ...
    celery -A workers.celery_app beat                              # exactly one per deployment

Queues (services.pipeline.STAGE_QUEUES): `gpu` (aerial SfM, 3DGS, view planning and rendering), `cpu`
(one task per rendered view, and the fan-out), `reduce` (reducer, combined SfM, finalize) and `control`
(the periodic reconcile and webhook deliveries: short tasks that must never wait behind a long stage,
so a light worker of their own serves them in docker-compose.yml and deploy/k8s). Settings come from
MIDVIEW_* (shared.config.Settings): broker_url, result_backend, and what the tasks need (database_url,
storage, work_dir, ...).

Delivery: tasks are acknowledged after they ran (acks_late) and requeued when their worker process dies
(reject_on_worker_lost), one message prefetched per process; every task is idempotent (stages skip what
is up to date), so a redelivery costs time, never correctness.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from celery import Celery
from celery.beat import PersistentScheduler
from celery.signals import worker_process_init, worker_ready, worker_shutdown
from kombu import Exchange, Queue

from services.pipeline import STAGE_QUEUES
from shared.config import Settings, get_settings

CONTROL_QUEUE = "control"
QUEUES = ("gpu", "cpu", "reduce", CONTROL_QUEUE)
DEFAULT_QUEUE = "reduce"
# a message not acknowledged within this time is delivered again (Redis transport): longer than any task
VISIBILITY_TIMEOUT_S = 6 * 3600
# with heartbeats every 10 s (settings.heartbeat_every_s, workers/tasks.py), heartbeat_timeout_s 30 s and
# reconcile every 15 s (settings.reconcile_every_s), a stage whose node died or whose message the broker
# lost is dispatched again within 30 + 15 s (and a ping's 2 s) of its last heartbeat
WEBHOOKS_EVERY_S = 15.0

# task names (stable: messages in the broker refer to them)
RUN_STAGE = "midview.run_stage"
FAN_OUT = "midview.fan_out"  # prepares a fan-out stage's units, then replaces itself by their chord
STAGE_UNIT = "midview.stage_unit"  # one unit of a fan-out stage (a block, a view)
FINALIZE = "midview.finalize"
RECONCILE = "midview.reconcile"
DELIVER_WEBHOOKS = "midview.deliver_webhooks"

TASK_QUEUES = {
    STAGE_UNIT: "cpu",  # the fan-out task sets each unit's queue (services.pipeline.FanOut.queue)
    FINALIZE: "reduce",
    RECONCILE: CONTROL_QUEUE,
    DELIVER_WEBHOOKS: CONTROL_QUEUE,
}


# task bookkeeping in Redis (workers/tasks.py writes it, the dispatcher and the reconciler read it)
TASKS_TTL_S = 7 * 24 * 3600
ALIVE_PATTERN = "midview:task:*:alive"


def tasks_key(job_id: str) -> str:
    """Redis set of the ids of a job's tasks (queued by the dispatcher, or running)."""
    return f"midview:job:{job_id}:tasks"


def alive_key(task_id: str) -> str:
    """Redis key present (with a TTL, refreshed) while a task runs: {job, task, args, pid, hostname}."""
    return f"midview:task:{task_id}:alive"


def redis_url(settings: Any) -> str | None:
    """The Redis holding task bookkeeping: the broker's, else the result backend's (None: neither)."""
    for url in (settings.broker_url, settings.result_backend):
        if url and url.split(":", 1)[0] in ("redis", "rediss"):
            return url
    return None


def route_task(name: str, args: Any, kwargs: Any, options: Any, task: Any = None, **kw: Any) -> dict | None:
    """Queue of a task: run_stage and fan_out by their stage (STAGE_QUEUES), the others by name.
    Signatures built by the dispatcher also carry an explicit queue, which wins."""
    if name in (RUN_STAGE, FAN_OUT):
        stage = (args[1] if args and len(args) > 1 else None) or (kwargs or {}).get("stage")
        if stage in STAGE_QUEUES:
            return {"queue": STAGE_QUEUES[stage]}
        return {"queue": "gpu"}
    if name in TASK_QUEUES:
        return {"queue": TASK_QUEUES[name]}
    return None


def celery_config(settings: Settings) -> dict[str, Any]:
    """The Celery configuration for settings (broker, backend, queues, routing, delivery, beat)."""
    return {
        "broker_url": settings.broker_url,
        "result_backend": settings.result_backend or settings.broker_url,
        "task_queues": [Queue(q, Exchange(q, type="direct"), routing_key=q) for q in QUEUES],
        "task_default_queue": DEFAULT_QUEUE,
        "task_default_exchange": DEFAULT_QUEUE,
        "task_default_routing_key": DEFAULT_QUEUE,
        "task_routes": (route_task,),
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "task_track_started": True,
        "worker_prefetch_multiplier": 1,
        "worker_cancel_long_running_tasks_on_connection_loss": True,
        "broker_connection_retry_on_startup": True,
        "broker_transport_options": {"visibility_timeout": VISIBILITY_TIMEOUT_S},
        "result_backend_transport_options": {"visibility_timeout": VISIBILITY_TIMEOUT_S},
        "task_serializer": "json",
        "result_serializer": "json",
        "accept_content": ["json"],
        "result_expires": 7 * 24 * 3600,
        "task_send_sent_event": False,
        "worker_hijack_root_logger": False,
        "timezone": "UTC",
        "enable_utc": True,
        "beat_scheduler": "workers.celery_app:Scheduler",
        "beat_schedule_filename": str(
            Path(settings.work_dir or Path(settings.data_dir) / "work") / "celerybeat-schedule"
        ),
        "beat_schedule": {
            "reconcile": {
                "task": RECONCILE,
                "schedule": settings.reconcile_every_s,
                "options": {"queue": CONTROL_QUEUE, "expires": settings.reconcile_every_s * 2},
            },
            "deliver_webhooks": {
                "task": DELIVER_WEBHOOKS,
                "schedule": WEBHOOKS_EVERY_S,
                "options": {"queue": CONTROL_QUEUE, "expires": WEBHOOKS_EVERY_S * 2},
            },
        },
    }


def make_app(
    settings: Settings | None = None,
    name: str = "midview",
    include: list[str] | None = None,
    set_as_current: bool = True,
) -> Celery:
    """A Celery app configured from settings (default: MIDVIEW_* of this process). Close an app made
    on the fly with app.close(), never app.pool.force_close_all(): kombu's connection pools are shared
    by every app of the process that has the same broker."""
    celery = Celery(name, include=include or [], set_as_current=set_as_current)
    celery.conf.update(celery_config(settings or get_settings()))
    return celery


# the workers' app (settings from MIDVIEW_*); the worker imports the tasks from workers.tasks
app = make_app(include=["workers.tasks"])


@worker_process_init.connect
def _reset_after_fork(**_: Any) -> None:
    """A pool process must not reuse database connections or clients created before the fork."""
    from shared.db.session import get_engine

    get_engine.cache_clear()
    from workers import tasks

    tasks.reset_clients()


_advertiser: Any = None


@worker_ready.connect
def _advertise(sender: Any = None, **_: Any) -> None:
    """The node offers its device and queues to the API (workers.offer) while it runs."""
    global _advertiser
    import redis

    from workers.offer import Advertiser

    url = redis_url(get_settings())
    if url is None or sender is None:
        return
    try:
        queues = [q.name for q in sender.task_consumer.queues]
    except AttributeError:
        queues = list(QUEUES)
    client = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5)
    _advertiser = Advertiser(client, str(sender.hostname), queues).start()


@worker_shutdown.connect
def _withdraw(**_: Any) -> None:
    if _advertiser is not None:
        _advertiser.stop()


class Scheduler(PersistentScheduler):
    """celery beat's persistent scheduler, creating the folder of its schedule file (under work_dir)."""

    def setup_schedule(self) -> None:
        Path(self.schedule_filename).parent.mkdir(parents=True, exist_ok=True)
        super().setup_schedule()
