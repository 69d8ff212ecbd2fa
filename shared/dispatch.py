"""How the API hands jobs to workers: a Dispatcher protocol and a registry of implementations.

The API creates the job row (status queued), commits, then calls `submit(job_id)`; `cancel` sets the
status to cancelled, commits, then calls `revoke(job_id)`; `rerun` resets the row with crud.rerun_job,
commits, then calls `submit(job_id, from_stage)`. An implementation therefore only moves work: the job
row is the source of truth, and workers report through shared.db.crud (start_stage, finish_stage,
update_job_progress, set_job_status, record_artifact). A worker must stop when crud raises
InvalidTransitionError (the job was cancelled meanwhile).

Implementations are looked up by name (`dispatcher` setting) and imported lazily, so that the API does
not import Celery unless it is used:

- "celery": the Celery canvas over the gpu/cpu/reduce queues (workers/dispatch.py);
- "embedded": an in-process worker thread for the single-machine default (workers/embedded.py).

`register_dispatcher(name, factory)` adds or replaces one (tests, plugins).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

DEFAULT_DISPATCHER = "embedded"


@runtime_checkable
class Dispatcher(Protocol):
    """Starts and stops the pipeline of a job that exists in the database."""

    def submit(self, job_id: str, from_stage: str | None = None) -> str | None:
        """Queue the job's stages (from from_stage on, else all); may return a task id (Celery root)."""
        ...

    def revoke(self, job_id: str) -> None:
        """Stop the job's queued and running tasks; must not fail when nothing is running."""
        ...

    # optional: profile() -> "cpu" | "gpu", the job profile its workers offer (offered_profile)


def offered_profile(dispatcher: Any) -> str:
    """The job profile the dispatcher's workers offer (its optional `profile()`: "cpu" or "gpu"); "cpu"
    when it has none or cannot tell."""
    probe = getattr(dispatcher, "profile", None)
    if not callable(probe):
        return "cpu"
    try:
        return "gpu" if probe() == "gpu" else "cpu"
    except Exception:
        logging.getLogger("midview.dispatch").exception("could not read the workers' profile")
        return "cpu"


class DispatcherError(RuntimeError):
    """No dispatcher of that name, or it could not be created."""


Factory = Callable[[Any], Dispatcher]

# name -> factory(settings) or "module:attribute" of one, imported on first use
_REGISTRY: dict[str, Factory | str] = {
    "celery": "workers.dispatch:CeleryDispatcher",
    "embedded": "workers.embedded:EmbeddedDispatcher",
}


def register_dispatcher(name: str, factory: Factory | str) -> None:
    """Add (or replace) a dispatcher: a callable taking the settings, or a "module:attribute" path."""
    _REGISTRY[name] = factory


def available_dispatchers() -> list[str]:
    return sorted(_REGISTRY)


def _resolve(name: str) -> Factory:
    try:
        entry = _REGISTRY[name]
    except KeyError:
        raise DispatcherError(
            f"unknown dispatcher {name!r}; known: {', '.join(available_dispatchers())}"
        ) from None
    if not isinstance(entry, str):
        return entry
    module, _, attr = entry.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as e:
        raise DispatcherError(f"dispatcher {name!r} ({entry}) is not available: {e}") from e


def get_dispatcher(settings: Any) -> Dispatcher:
    """The dispatcher named by `settings.dispatcher` (default "embedded"), created with the settings."""
    name = getattr(settings, "dispatcher", None) or DEFAULT_DISPATCHER
    dispatcher = _resolve(name)(settings)
    if not isinstance(dispatcher, Dispatcher):
        raise DispatcherError(f"dispatcher {name!r} does not implement submit() and revoke()")
    return dispatcher
