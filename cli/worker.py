"""`midview worker`: a Celery worker of the pipeline queues (settings from MIDVIEW_*: broker_url,
result_backend, database_url, storage, work_dir, ...).

Register in cli/main.py:

    from cli import worker as worker_cli
    app.command("worker")(worker_cli.worker)

    midview worker --queues gpu --concurrency 1            # a GPU machine: SfM, 3DGS, rendering
    midview worker --queues cpu,reduce --concurrency 4     # CPU machines: per-view matching, reducer
    midview worker --queues control --beat                 # one per deployment: the periodic tasks
"""

from __future__ import annotations

from typing import Annotated

import typer

ALL_QUEUES = "gpu,cpu,reduce,control"


def worker_argv(
    queues: str = ALL_QUEUES,
    concurrency: int = 1,
    beat: bool = False,
    loglevel: str = "INFO",
    pool: str = "prefork",
    hostname: str | None = None,
) -> list[str]:
    """The `celery worker` arguments; ValueError for an unknown queue."""
    from workers.celery_app import QUEUES

    names = [q.strip() for q in queues.split(",") if q.strip()]
    bad = [q for q in names if q not in QUEUES]
    if not names or bad:
        raise ValueError(f"unknown queue(s) {bad or names}: queues are {', '.join(QUEUES)}")
    argv = ["worker", "-Q", ",".join(names), "-c", str(int(concurrency)), "-P", pool, "-l", loglevel]
    if hostname:
        argv += ["-n", hostname]
    if beat:
        argv.append("-B")
    return argv


def worker(
    queues: Annotated[
        str, typer.Option(help="Comma-separated queues: gpu, cpu, reduce, control (periodic tasks)")
    ] = ALL_QUEUES,
    concurrency: Annotated[int, typer.Option(help="Worker processes (1 per GPU on gpu queues)")] = 1,
    beat: Annotated[
        bool, typer.Option(help="Also run the periodic tasks (reconcile, webhooks): one per deployment")
    ] = False,
    loglevel: Annotated[str, typer.Option(help="Celery log level")] = "INFO",
    pool: Annotated[str, typer.Option(help="Celery pool: prefork, solo, threads")] = "prefork",
    hostname: Annotated[str | None, typer.Option(help="Worker node name (-n), e.g. gpu1@%h")] = None,
) -> None:
    """Run a Celery worker of the pipeline."""
    try:
        argv = worker_argv(queues, concurrency, beat, loglevel, pool, hostname)
    except ValueError as e:
        typer.secho(str(e), fg="red", err=True)
        raise typer.Exit(2) from None
    from workers.celery_app import app

    app.worker_main(argv)
