"""Content digests of files (sha256), remembered by size, modification and change times and inode in a
small JSON file, so that a file is hashed again only when it changed (the change time moves on any
write and cannot be set back, unlike the modification time). What the pipeline's stage fingerprints and
the features cache compare: the content, whatever machine wrote the file and when.

    with DigestCache(job_root / ".digests.json") as dc:
        dc.digest(path)                      # sha256 hex of the file's bytes
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path
from typing import Any

CHUNK = 1 << 20


def sha256_file(path: str | Path) -> str:
    """The sha256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(CHUNK), b""):
            h.update(chunk)
    return h.hexdigest()


class DigestCache:
    """sha256 of files, cached in `path` (JSON {absolute path: [size, mtime_ns, ctime_ns, inode,
    sha256]}; None: in memory only). A file whose size, times or inode changed is hashed again. Saved on
    exit (atomically; a concurrent writer may win, which only costs a later re-hash)."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else None
        self.entries: dict[str, list[Any]] = {}
        self.changed = False
        if self.path is not None and self.path.is_file():
            with contextlib.suppress(ValueError, OSError):
                self.entries = dict(json.loads(self.path.read_text()))

    def __enter__(self) -> DigestCache:
        return self

    def __exit__(self, *exc: object) -> None:
        self.save()

    def digest(self, path: str | Path) -> str:
        """The sha256 (hex) of the file at `path`, from the cache when the file did not change."""
        key = os.path.abspath(path)
        st = os.stat(key)
        stamp = [int(st.st_size), int(st.st_mtime_ns), int(st.st_ctime_ns), int(st.st_ino)]
        known = self.entries.get(key)
        if known is not None and known[:4] == stamp:
            return str(known[4])
        sha = sha256_file(key)
        self.entries[key] = [*stamp, sha]
        self.changed = True
        return sha

    def save(self) -> None:
        if self.path is None or not self.changed:
            return
        with contextlib.suppress(OSError):
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(self.entries))
            tmp.replace(self.path)
        self.changed = False
