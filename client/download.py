"""Download a job's artifacts to a folder, each checked against the size and sha256 the API lists;
files already there with the right digest are not fetched again."""

from __future__ import annotations

import fnmatch
from pathlib import Path

from client.http import MidviewClient
from client.uploads import sha256_file


def download_job(mv: MidviewClient, job_id: str, dest: Path, patterns: list[str] | None = None) -> list[Path]:
    """The job's artifacts (those whose name matches one of the glob patterns, default all) under
    dest/NAME (e.g. dest/combined/gis/cameras.gpkg); ValueError when a download's digest is wrong."""
    dest = Path(dest)
    out = []
    for art in mv.artifacts(job_id):
        if patterns and not any(fnmatch.fnmatch(art["name"], p) for p in patterns):
            continue
        target = (dest / art["name"]).resolve()
        if dest.resolve() not in target.parents:  # a name with .. cannot leave the folder
            raise ValueError(f"artifact name {art['name']!r} leaves {dest}")
        if target.is_file() and art["sha256"] and sha256_file(target) == art["sha256"]:
            out.append(target)
            continue
        if not art["download_url"]:
            raise ValueError(f"artifact {art['name']} has no download URL")
        mv.download_to(art["download_url"], target)
        if art["sha256"] and sha256_file(target) != art["sha256"]:
            target.unlink()
            raise ValueError(f"{art['name']}: the downloaded bytes do not match the listed sha256")
        out.append(target)
    return out
