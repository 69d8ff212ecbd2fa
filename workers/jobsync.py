"""A job folder on a worker's local disk, mirrored to and from the job's storage prefix.

Layout in storage (`P` = shared.storage.keys.job_prefix(tenant, project, job)):

    P/files/REL          a file of the job folder (REL: `sfm/sparse/cameras.bin`, `stages/aerial_sfm.json`)
    P/manifests/UNIT.json  what one push (a stage, one view of match_views) uploaded:
                         {"unit", "created_ns", "files": {REL: [size, sha256]}}

and on the worker (`ROOT` = work_dir/JOB_ID):

    ROOT/inputs/{aerial,ground}/NAME   the project's images, downloaded (services.pipeline links them)
    ROOT/inputs/pos.csv                the project's POS rows (services.pos.write_pos_csv)
    ROOT/inputs/cameras.json           the project's cameras.json, when storage holds one (CAMERAS_FILE)
    ROOT/...                           the services.pipeline job folder
    ROOT/.sync.json                    {REL: [size, sha256]} of the files this folder shares with storage
    ROOT/.digests.json                 content digests by file stat (services.digests), shared with the
                                       pipeline's fingerprints

The pipeline skips a stage whose input fingerprint (names, sizes and contents of its input files)
matches its marker, so every worker that holds the same files computes the same fingerprints, whenever
it downloaded them. A file is transferred only when its content differs (size and sha256).
"""

from __future__ import annotations

import fnmatch
import json
import logging
import shutil
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from services.digests import DigestCache
from services.pipeline import JobOptions
from shared.db import crud
from shared.db.models import Job as JobRow
from shared.storage import Storage, StorageKeyError
from shared.storage.keys import cameras_key

log = logging.getLogger("midview.workers.jobsync")

SYNC_FILE = ".sync.json"
FILES_DIR = "files/"
MANIFESTS_DIR = "manifests/"
INPUTS = "inputs"
CAMERAS_FILE = "cameras.json"  # optional object at project_prefix(...)/cameras.json: intrinsics per set
# never pushed: the inputs (they come from the image rows), the links, local state, 3DGS checkpoints
# (fnmatch patterns: a path at or under one is local)
LOCAL_ONLY = (INPUTS, "images", "job.json", SYNC_FILE, "splat/ckpts", "blocks/*/ckpts")
_TEMP_SUFFIXES = (".tmp", "-wal", "-shm", "-journal")
_THREADS = 8

CONTENT_TYPES = {
    ".json": "application/json",
    ".geojson": "application/geo+json",
    ".h5": "application/x-hdf5",
    ".csv": "text/csv",
    ".txt": "text/plain",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".db": "application/vnd.sqlite3",
}


def content_type(path: str | Path) -> str:
    return CONTENT_TYPES.get(Path(path).suffix.lower(), "application/octet-stream")


def job_root(work_dir: str | Path, job_id: str) -> Path:
    return Path(work_dir) / str(job_id)


def job_storage_prefix(job_row: JobRow) -> str:
    """`tenants/T/projects/P/jobs/J/` of a job row."""
    from shared.storage.keys import job_prefix

    return job_prefix(job_row.project.tenant_id, job_row.project_id, job_row.id)


def files_key(prefix: str, rel: str) -> str:
    return f"{prefix}{FILES_DIR}{rel}"


def digests(root: Path) -> DigestCache:
    """The job folder's content digests (ROOT/.digests.json, also the pipeline's)."""
    from services.pipeline import DIGESTS_FILE

    return DigestCache(Path(root) / DIGESTS_FILE)


def _stat(path: Path, dc: DigestCache) -> list[Any]:
    """[size, sha256] of a file: what the manifests and .sync.json compare."""
    return [int(path.stat().st_size), dc.digest(path)]


@contextmanager
def locked(root: str | Path) -> Iterator[None]:
    """An exclusive lock on a job folder (fcntl), held while it is synced: several worker processes of
    one machine may work on the same job (match_views fan-out with concurrency > 1)."""
    import fcntl

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    with open(root / ".lock", "a+b") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


# -- local sync state ----------------------------------------------------------------------------
def read_sync(root: Path) -> dict[str, list[Any]]:
    try:
        doc = json.loads((root / SYNC_FILE).read_text())
        return {k: [int(v[0]), v[1]] for k, v in doc.items()}
    except (FileNotFoundError, ValueError, TypeError, IndexError):
        return {}


def write_sync(root: Path, sync: dict[str, list[Any]]) -> None:
    root.mkdir(parents=True, exist_ok=True)
    tmp = root / f"{SYNC_FILE}.tmp"
    tmp.write_text(json.dumps(dict(sorted(sync.items()))))
    tmp.replace(root / SYNC_FILE)


# -- inputs --------------------------------------------------------------------------------------
def pipeline_settings(settings: Any) -> dict:
    """The job folder's pipeline settings (services.pipeline DEFAULT_SETTINGS overrides) on this worker.
    Only knobs that enter no stage conf belong here: every worker must compute the same fingerprints."""
    n = int(getattr(settings, "num_threads", 0) or 0)
    return {"torch_threads": n or None}


def _pos_records(session: Session, project_id: str, names: set[str]) -> list:
    import numpy as np

    from services.pos import PosRecord

    out = []
    for row in crud.list_pos_records(session, project_id):
        if row.image_name not in names:
            continue
        R = np.asarray(row.attitude, dtype=np.float64) if row.attitude is not None else None
        out.append(PosRecord(row.image_name, row.lat, row.lon, row.h, R, row.std_xy, row.std_z, row.std_att))
    return out


def _write_if_changed(path: Path, data: bytes) -> None:
    """Write data unless the file holds it already (left untouched then)."""
    if not (path.is_file() and path.read_bytes() == data):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_bytes(data)
        tmp.replace(path)


class InputsChanged(RuntimeError):
    """A job's images or POS differ from the snapshot it was created on."""


def materialize(
    session: Session,
    storage: Storage,
    job_row: JobRow,
    work_dir: str | Path,
    settings: dict | None = None,
) -> Any:
    """The job's pipeline folder on this worker: images downloaded into ROOT/inputs (skipped when present
    with the same size and sha256), the POS rows as ROOT/inputs/pos.csv, the project's cameras.json
    when storage has one, and the services.pipeline.Job created (or refreshed) with the row's options."""
    from services import pipeline
    from services.pos import write_pos_csv

    root = job_root(work_dir, job_row.id)
    inputs = root / INPUTS
    project = job_row.project
    images = crud.list_images(session, project.id)
    changed = crud.inputs_changed(session, job_row, images)
    if changed:
        raise InputsChanged(
            f"job {job_row.id}: its inputs changed since it was created: {'; '.join(changed)}"
        )
    if job_row.inputs:  # the images the job was created on, not those uploaded since
        images = [im for im in images if im.name in job_row.inputs.get("images", {})]
    names = {im.name for im in images}
    todo = []
    for s in ("aerial", "ground"):
        (inputs / s).mkdir(parents=True, exist_ok=True)
    with digests(root) as dc:
        for im in images:
            path = inputs / im.name
            if path.is_file() and _stat(path, dc) == [int(im.size_bytes), im.sha256]:
                continue
            todo.append((im.storage_key, path))
    _parallel(lambda item: storage.download(*item), todo)
    for s in ("aerial", "ground"):  # images removed from the project since the last run
        for p in (inputs / s).iterdir():
            if p.is_file() and f"{s}/{p.name}" not in names:
                p.unlink()
    if todo:
        log.info("job %s: downloaded %d of %d images", job_row.id, len(todo), len(images))

    # POS: written to a scratch file, kept (with its time) when the content did not change
    pos = inputs / "pos.csv"
    scratch = inputs / ".pos.csv.new"
    write_pos_csv(scratch, _pos_records(session, project.id, names))
    _write_if_changed(pos, scratch.read_bytes())
    scratch.unlink()

    cameras = inputs / CAMERAS_FILE
    try:
        _write_if_changed(cameras, storage.get_bytes(cameras_key(project.tenant_id, project.id)))
    except StorageKeyError:
        cameras.unlink(missing_ok=True)

    options = JobOptions.model_validate(job_row.options or {})
    return pipeline.Job.create(
        root,
        inputs / "aerial",
        inputs / "ground",
        pos,
        cameras if cameras.is_file() else None,
        options=options,
        settings=settings or {},
    )


# -- pull and push -------------------------------------------------------------------------------
@dataclass
class SyncStats:
    transferred: list[str] = field(default_factory=list)
    skipped: int = 0
    deleted: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def __str__(self) -> str:
        return (
            f"{len(self.transferred)} transferred, {self.skipped} unchanged, {len(self.deleted)} deleted "
            f"in {self.seconds:.1f} s"
        )


def _parallel(fn: Any, items: list) -> None:
    if len(items) <= 1:
        for it in items:
            fn(it)
        return
    with ThreadPoolExecutor(min(_THREADS, len(items))) as pool:
        for _ in pool.map(fn, items):
            pass


def read_manifests(storage: Storage, prefix: str) -> dict[str, list[Any]]:
    """{REL: [size, sha256]} merged over every manifest under the prefix, the newest winning."""
    docs = []
    for key in storage.list(f"{prefix}{MANIFESTS_DIR}"):
        try:
            docs.append(json.loads(storage.get_bytes(key)))
        except (StorageKeyError, ValueError):
            continue  # deleted meanwhile, or not ours
    merged: dict[str, list[Any]] = {}
    for doc in sorted(docs, key=lambda d: int(d.get("created_ns", 0))):
        for rel, v in (doc.get("files") or {}).items():
            merged[rel] = [int(v[0]), v[1]]
    return merged


def pull(storage: Storage, prefix: str, root: str | Path) -> SyncStats:
    """Bring the job folder up to date with storage: download every object under P/files/ that is
    missing here or differs (size, and content where a manifest gives its sha256), and delete local
    files that came from storage earlier but are gone there now. Files that never were in storage
    (local scratch) are left alone."""
    t0 = time.perf_counter()
    root = Path(root)
    stats = SyncStats()
    fprefix = f"{prefix}{FILES_DIR}"
    keys = storage.list(fprefix)
    expected = read_manifests(storage, prefix)
    old = read_sync(root)
    sync: dict[str, list[Any]] = {}
    todo = []
    with digests(root) as dc:
        for key in keys:
            rel = key[len(fprefix) :]
            path = root / rel
            want = expected.get(rel)
            if want is None:  # pushed without a manifest (interrupted push): compare sizes only
                size = storage.stat(key).size
                if path.is_file() and path.stat().st_size == size:
                    sync[rel] = _stat(path, dc)
                    stats.skipped += 1
                    continue
            elif path.is_file() and _stat(path, dc) == want:
                sync[rel] = want
                stats.skipped += 1
                continue
            todo.append((key, rel))

        def fetch(item: tuple[str, str]) -> None:
            key, rel = item
            path = root / rel
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            storage.download(key, path)

        _parallel(fetch, todo)
        for _, rel in todo:
            sync[rel] = _stat(root / rel, dc)
            stats.transferred.append(rel)
    for rel in sorted(set(old) - set(sync)):  # gone from storage since we last saw it
        p = root / rel
        if p.is_file():
            p.unlink()
            stats.deleted.append(rel)
    write_sync(root, sync)
    stats.seconds = time.perf_counter() - t0
    return stats


def _local_only(rel: str) -> bool:
    name = rel.rsplit("/", 1)[-1]
    if name.startswith(".") or name.endswith(_TEMP_SUFFIXES):
        return True
    return any(fnmatch.fnmatchcase(rel, p) or fnmatch.fnmatchcase(rel, p + "/*") for p in LOCAL_ONLY)


def local_files(root: Path, paths: Iterable[str | Path]) -> dict[str, Path]:
    """{REL: path} of the files at or under paths (relative to root or absolute inside it)."""
    root = Path(root)
    out: dict[str, Path] = {}
    for p in paths:
        p = Path(p)
        p = p if p.is_absolute() else root / p
        if p.is_file():
            cand = [p]
        elif p.is_dir():
            cand = sorted(q for q in p.rglob("*") if q.is_file())
        else:
            continue
        for q in cand:
            rel = q.relative_to(root).as_posix()
            if not _local_only(rel):
                out[rel] = q
    return out


def push(
    storage: Storage,
    prefix: str,
    root: str | Path,
    paths: Iterable[str | Path],
    unit: str,
    mirror: Iterable[str] = (),
) -> SyncStats:
    """Upload the files at or under paths (skipping those storage already holds unchanged, per
    .sync.json), then the unit's manifest {REL: [size, sha256]} (merged with the unit's previous one).
    For each folder in `mirror` (relative to root), objects under it that no longer exist here are
    deleted from storage (e.g. the matches of views no longer planned)."""
    t0 = time.perf_counter()
    root = Path(root)
    stats = SyncStats()
    files = local_files(root, paths)
    sync = read_sync(root)
    with digests(root) as dc:
        current = {rel: _stat(p, dc) for rel, p in files.items()}
    todo = [rel for rel, st in current.items() if sync.get(rel) != st]
    stats.skipped = len(current) - len(todo)

    def put(rel: str) -> None:
        storage.put_file(files_key(prefix, rel), files[rel], content_type=content_type(rel))

    _parallel(put, todo)
    for rel in todo:
        sync[rel] = current[rel]
    stats.transferred = todo
    fprefix = f"{prefix}{FILES_DIR}"
    for folder in mirror:
        folder = str(folder).strip("/")
        for key in storage.list(f"{fprefix}{folder}/"):
            rel = key[len(fprefix) :]
            if not (root / rel).is_file():
                storage.delete(key)
                sync.pop(rel, None)
                stats.deleted.append(rel)
    key = f"{prefix}{MANIFESTS_DIR}{unit}.json"
    try:  # a unit pushed again keeps the entries of its files not pushed this time
        entries = dict(json.loads(storage.get_bytes(key)).get("files") or {})
    except (StorageKeyError, ValueError):
        entries = {}
    entries.update(current)
    for rel in stats.deleted:
        entries.pop(rel, None)
    manifest = {"unit": unit, "created_ns": time.time_ns(), "files": entries}
    storage.put_bytes(key, json.dumps(manifest).encode(), content_type="application/json")
    write_sync(root, sync)
    stats.seconds = time.perf_counter() - t0
    return stats


def delete_manifests(storage: Storage, prefix: str, unit_prefix: str) -> int:
    """Delete the manifests of units whose name starts with unit_prefix (superseded by a later push)."""
    keys = storage.list(f"{prefix}{MANIFESTS_DIR}{unit_prefix}")
    for k in keys:
        storage.delete(k)
    return len(keys)
