"""Objects as files under a root folder (the embedded default): atomic writes, multipart in a parts folder."""

from __future__ import annotations

import builtins
import hashlib
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO

from shared.storage.base import ObjectStat, PartStat, Storage, StorageKeyError, check_part_number
from shared.storage.keys import InvalidKeyError, validate_key, validate_prefix

CHUNK = 1024 * 1024
TMP_DIR, UPLOADS_DIR = ".tmp", ".uploads"  # reserved top-level folders, never listed


class LocalStorage(Storage):
    """Storage in a local folder; keys map to relative paths under root."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        (self.root / TMP_DIR).mkdir(parents=True, exist_ok=True)
        (self.root / UPLOADS_DIR).mkdir(parents=True, exist_ok=True)

    def __repr__(self) -> str:
        return f"LocalStorage({str(self.root)!r})"

    # paths
    def _path(self, key: str) -> Path:
        validate_key(key)
        if key.split("/", 1)[0] in (TMP_DIR, UPLOADS_DIR):
            raise InvalidKeyError(f"key {key!r}: {TMP_DIR}/ and {UPLOADS_DIR}/ are reserved")
        return self.root.joinpath(*key.split("/"))

    def _existing(self, key: str) -> Path:
        path = self._path(key)
        if not path.is_file():
            raise StorageKeyError(f"no object {key!r} in {self.root}")
        return path

    @contextmanager
    def _atomic(self, dest: Path) -> Iterator[BinaryIO]:
        """A temporary file renamed onto dest when the block succeeds, removed when it fails."""
        fd, tmp = tempfile.mkstemp(dir=self.root / TMP_DIR)
        try:
            with os.fdopen(fd, "wb") as f:
                yield f
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, dest)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    def _stat(self, key: str, path: Path) -> ObjectStat:
        st = path.stat()
        return ObjectStat(
            key=key,
            size=st.st_size,
            etag=f"{st.st_size:x}-{st.st_mtime_ns:x}",
            last_modified=datetime.fromtimestamp(st.st_mtime, UTC),
        )

    # objects
    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> ObjectStat:
        path = self._path(key)
        with self._atomic(path) as f:
            f.write(data)
        return self._stat(key, path)

    def put_file(self, key: str, path: str | Path, content_type: str | None = None) -> ObjectStat:
        with open(path, "rb") as src:
            return self.put_stream(key, src)

    def put_stream(self, key: str, fileobj: BinaryIO, content_type: str | None = None) -> ObjectStat:
        path = self._path(key)
        with self._atomic(path) as f:
            shutil.copyfileobj(fileobj, f, CHUNK)
        return self._stat(key, path)

    def get_bytes(self, key: str) -> bytes:
        return self._existing(key).read_bytes()

    def download(self, key: str, path: str | Path) -> Path:
        src, dest = self._existing(key), Path(path)
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.")
        os.close(fd)
        try:
            shutil.copyfile(src, tmp)
            os.replace(tmp, dest)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return dest

    def open_read(self, key: str) -> BinaryIO:
        return open(self._existing(key), "rb")  # the caller closes it

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def stat(self, key: str) -> ObjectStat:
        return self._stat(key, self._existing(key))

    def list(self, prefix: str = "") -> list[str]:
        validate_prefix(prefix)
        folder = prefix.rsplit("/", 1)[0] if "/" in prefix else ""
        base = self.root.joinpath(*folder.split("/")) if folder else self.root
        if not base.is_dir():
            return []
        out = []
        for dirpath, dirnames, filenames in os.walk(base):
            rel_dir = Path(dirpath).relative_to(self.root).as_posix()
            if rel_dir == ".":
                dirnames[:] = [d for d in dirnames if d not in (TMP_DIR, UPLOADS_DIR)]
                rel_dir = ""
            for name in filenames:
                key = f"{rel_dir}/{name}" if rel_dir else name
                if key.startswith(prefix):
                    out.append(key)
        return sorted(out)

    def delete(self, key: str) -> None:
        path = self._path(key)
        path.unlink(missing_ok=True)
        self._prune(path.parent)

    def delete_prefix(self, prefix: str) -> int:
        if not validate_prefix(prefix):
            raise ValueError("delete_prefix needs a non-empty prefix")
        keys = self.list(prefix)
        for key in keys:
            self.delete(key)
        return len(keys)

    def _prune(self, folder: Path) -> None:
        """Remove empty folders from folder up to (not including) the root."""
        while folder != self.root and self.root in folder.parents:
            try:
                folder.rmdir()
            except OSError:
                return
            folder = folder.parent

    # URLs
    def presigned_get_url(self, key: str, expires_s: int | None = None) -> str | None:
        """A `file://` URL of the object (no expiry): only meaningful on this machine."""
        return self._existing(key).as_uri()

    # multipart
    def _upload_dir(self, key: str, upload_id: str) -> Path:
        validate_key(key)
        if not upload_id or not all(c in "0123456789abcdef" for c in upload_id):
            raise StorageKeyError(f"no multipart upload {upload_id!r}")
        folder = self.root / UPLOADS_DIR / upload_id
        try:
            meta = json.loads((folder / "upload.json").read_text())
        except FileNotFoundError:
            raise StorageKeyError(f"no multipart upload {upload_id!r} for {key!r}") from None
        if meta["key"] != key:
            raise StorageKeyError(f"multipart upload {upload_id!r} is for {meta['key']!r}, not {key!r}")
        return folder

    def create_multipart(self, key: str, content_type: str | None = None) -> str:
        self._path(key)
        upload_id = uuid.uuid4().hex
        folder = self.root / UPLOADS_DIR / upload_id
        folder.mkdir()
        (folder / "upload.json").write_text(json.dumps({"key": key, "content_type": content_type}))
        return upload_id

    def presigned_part_url(
        self,
        key: str,
        upload_id: str,
        part_number: int,
        expires_s: int | None = None,
        size: int | None = None,
    ) -> str | None:
        """None: local parts go through upload_part (the API receives them)."""
        self._upload_dir(key, upload_id)
        check_part_number(part_number)
        return None

    def upload_part(self, key: str, upload_id: str, part_number: int, data: bytes | BinaryIO) -> str:
        folder = self._upload_dir(key, upload_id)
        n = check_part_number(part_number)
        md5 = hashlib.md5(usedforsecurity=False)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".part.")
        try:
            with os.fdopen(fd, "wb") as f:
                chunks = (
                    [data] if isinstance(data, bytes | bytearray) else iter(lambda: data.read(CHUNK), b"")
                )
                for chunk in chunks:
                    md5.update(chunk)
                    f.write(chunk)
            etag = md5.hexdigest()
            (folder / f"{n:05d}.etag").write_text(etag)
            os.replace(tmp, folder / f"{n:05d}.part")
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return etag

    def list_parts(
        self, key: str, upload_id: str, etags: Mapping[int, str] | None = None
    ) -> builtins.list[PartStat]:
        """One file per part number: a part sent again replaces the earlier one."""
        folder = self._upload_dir(key, upload_id)
        out = []
        for part in sorted(folder.glob("[0-9]" * 5 + ".part")):
            try:
                etag = part.with_suffix(".etag").read_text()
                st = part.stat()
            except FileNotFoundError:  # being replaced, or the upload finished meanwhile
                continue
            modified = datetime.fromtimestamp(st.st_mtime, UTC)
            out.append(PartStat(int(part.stem), st.st_size, etag, modified))
        return out

    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> ObjectStat:
        folder = self._upload_dir(key, upload_id)
        if not parts:
            raise ValueError("complete_multipart needs at least one part")
        parts = sorted((check_part_number(n), etag) for n, etag in parts)
        numbers = [n for n, _ in parts]
        if len(set(numbers)) != len(numbers):
            raise ValueError(f"repeated part numbers in {numbers}")
        for n, etag in parts:
            stored = folder / f"{n:05d}.etag"
            if not stored.is_file():
                raise StorageKeyError(f"part {n} of upload {upload_id!r} was never uploaded")
            if stored.read_text() != etag.strip('"'):
                raise ValueError(f"part {n}: ETag {etag!r} does not match the uploaded part")
        path = self._path(key)
        with self._atomic(path) as out:
            for n in numbers:
                with open(folder / f"{n:05d}.part", "rb") as f:
                    shutil.copyfileobj(f, out, CHUNK)
        shutil.rmtree(folder, ignore_errors=True)
        return self._stat(key, path)

    def abort_multipart(self, key: str, upload_id: str) -> None:
        shutil.rmtree(self._upload_dir(key, upload_id))
