"""Running stages in-process: input fingerprints, done markers, and the runner (`midview run`, and the
Celery workers stage by stage)."""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from services.pipeline.job import Job
from services.pipeline.registry import OPTIONAL_STAGES, REGISTRY, STAGES
from services.pipeline.stages import StageError, set_threads

Progress = Callable[[str, float, str], None]


# -- fingerprints and markers --------------------------------------------------------------------
_SKIP_SUFFIXES = (".tmp", "-wal", "-shm", "-journal")


def _files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if not path.is_dir():
        return []
    out = []
    for dirpath, dirnames, filenames in os.walk(path, followlinks=True):
        dirnames.sort()
        for f in sorted(filenames):
            if f.startswith(".") or f.endswith(_SKIP_SUFFIXES):
                continue
            out.append(Path(dirpath) / f)
    return out


DIGESTS_FILE = ".digests.json"  # the job folder's content digests, by file stat (services.digests)


def fingerprint(conf: Any, inputs: list[Path], root: Path | None = None) -> str:
    """sha256 of the conf (JSON) and of the inputs' file names, sizes and contents (sha256, cached by
    file stat in ROOT/.digests.json). Names under `root` (the job folder) are taken relative to it, so
    that a job folder can be moved, or its stage folders shared with another job through links; the
    same files give the same fingerprint on every machine, whenever they were written."""
    from services.digests import DigestCache

    def name(p: Path) -> str:
        if root is not None:
            try:
                return str(Path(os.path.abspath(p)).relative_to(os.path.abspath(root)))
            except ValueError:
                pass
        return str(p)

    h = hashlib.sha256()
    h.update(json.dumps(conf, sort_keys=True, default=str).encode())
    with DigestCache(Path(root) / DIGESTS_FILE if root is not None else None) as dc:
        for p in inputs:
            p = Path(p)
            h.update(f"#{name(p)}".encode())
            for f in _files(p):
                try:
                    size, sha = f.stat().st_size, dc.digest(f)
                except FileNotFoundError:
                    continue
                h.update(f"{name(f)}:{size}:{sha}\n".encode())
    return h.hexdigest()


def marker_path(job: Job, stage: str) -> Path:
    return job.stages_dir / f"{stage}.json"


def read_marker(job: Job, stage: str) -> dict | None:
    try:
        return json.loads(marker_path(job, stage).read_text())
    except (FileNotFoundError, ValueError):
        return None


def is_done(job: Job, stage: str) -> bool:
    """Whether the stage's outputs exist and were made from the current inputs and conf."""
    sd = REGISTRY[stage]
    m = read_marker(job, stage)
    if m is None or any(not Path(p).exists() for p in sd.outputs(job)):
        return False
    return m.get("fingerprint") == fingerprint(sd.conf(job), sd.inputs(job), job.root)


class StageInputsMissing(StageError):
    """A stage was asked for before the stages that make its inputs."""


def check_inputs(job: Job, stage: str) -> None:
    """Raise StageInputsMissing when an input that another stage makes does not exist yet."""
    need: dict[str, list[str]] = {}
    for p in REGISTRY[stage].inputs(job):
        if Path(p).exists():
            continue
        for other, sd in REGISTRY.items():
            if other != stage and any(
                Path(p) == Path(o) or Path(o) in Path(p).parents for o in sd.outputs(job)
            ):
                need.setdefault(other, []).append(str(Path(p).relative_to(job.root)))
                break
    if need:
        made = "; ".join(
            f"{', '.join(v)} (made by {k})"
            for k, v in sorted(need.items(), key=lambda kv: STAGES.index(kv[0]))
        )
        raise StageInputsMissing(f"stage {stage} needs {made}: run those stages first")


def run_stage(job: Job, stage: str, progress: Progress | None = None, force: bool = False) -> dict:
    """Run one stage unless it is up to date; returns its marker (with "skipped": True when skipped)."""
    sd = REGISTRY[stage]
    prog = progress or (lambda s, f, m: None)
    if not force and is_done(job, stage):
        m = read_marker(job, stage) or {}
        prog(stage, 1.0, "up to date")
        return {**m, "skipped": True}
    check_inputs(job, stage)
    prog(stage, 0.0, "started")
    t0 = time.perf_counter()
    set_threads(job)  # every stage: torch's default threads beside another process stall 5x (plan_views)
    summary = sd.run(job, lambda f, m: prog(stage, float(min(max(f, 0.0), 1.0)), m))
    missing = [str(p) for p in sd.outputs(job) if not Path(p).exists()]
    if missing:
        raise RuntimeError(f"stage {stage} finished without its outputs: {missing}")
    marker = write_marker(job, stage, summary, seconds=round(time.perf_counter() - t0, 2))
    prog(stage, 1.0, "finished")
    return {**marker, "skipped": False}


def write_marker(job: Job, stage: str, summary: Any, seconds: float) -> dict:
    """Record a finished stage (atomically): its input fingerprint, outputs, duration and summary."""
    sd = REGISTRY[stage]
    marker = {
        "stage": stage,
        "fingerprint": fingerprint(sd.conf(job), sd.inputs(job), job.root),
        "outputs": [str(p) for p in sd.outputs(job)],
        "seconds": seconds,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "summary": summary,
    }
    job.stages_dir.mkdir(parents=True, exist_ok=True)
    tmp = marker_path(job, stage).with_suffix(".json.tmp")
    tmp.write_text(json.dumps(marker, indent=1, default=str))
    tmp.replace(marker_path(job, stage))
    return marker


def mark_done(job: Job, stage: str, summary: dict | None = None) -> dict:
    """Record a stage as done with the outputs already in place (e.g. an aerial model or a 3DGS model
    made elsewhere and copied into the job folder); its marker gets the current input fingerprint."""
    sd = REGISTRY[stage]
    missing = [str(p) for p in sd.outputs(job) if not Path(p).exists()]
    if missing:
        raise FileNotFoundError(f"stage {stage}: outputs missing: {missing}")
    marker = write_marker(job, stage, {**(summary or {}), "adopted": True}, seconds=0.0)
    return marker


def run(
    job: Job | str | Path,
    stages: list[str] | None = None,
    from_stage: str | None = None,
    progress: Progress | None = None,
    force: bool = False,
) -> dict[str, dict]:
    """Run the job's stages in order (job.options.stages, or `stages`, from `from_stage` on; stages
    before it must be done). Returns {stage: marker} with "skipped" set for the stages that were up to
    date."""
    job = job if isinstance(job, Job) else Job.load(job)
    if stages is None:
        stages = job.options.stages_from(from_stage)
    elif from_stage is not None:
        stages = stages[stages.index(from_stage) :]
    unknown = [s for s in stages if s not in REGISTRY]
    if unknown:
        raise ValueError(f"unknown stages {unknown}; stages are {list(STAGES)}")
    results = {}
    for s in sorted(stages, key=STAGES.index):
        results[s] = run_stage(job, s, progress, force=force and (from_stage is None or s == from_stage))
    return results


def status(job: Job | str | Path) -> dict[str, str]:
    """{stage: "done" | "stale" | "pending"} of a job folder (optional stages only when selected or
    run)."""
    job = job if isinstance(job, Job) else Job.load(job)
    out = {}
    for s in STAGES:
        marker = read_marker(job, s)
        if marker is None and s in OPTIONAL_STAGES and s not in job.options.stages:
            continue
        if marker is None:
            out[s] = "pending"
        else:
            out[s] = "done" if is_done(job, s) else "stale"
    return out
