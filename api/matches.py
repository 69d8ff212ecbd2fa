"""Reading a job's match file (shared/matchfile.py, docs/formats.md) for the pairs endpoints.

The HDF5 file is fetched once from storage into a local cache (keyed by artifact id and version) since
h5py needs a seekable local file."""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any

from shared.db.models import Artifact
from shared.matchfile import MatchFile
from shared.storage import Storage

MATCH_KINDS = ("matches",)
_lock = threading.Lock()


def _image_set(name: str) -> str:
    return name.split("/", 1)[0]


def local_copy(storage: Storage, artifact: Artifact, cache_dir: Path) -> Path:
    """A local file with the artifact's bytes (downloaded on first use; older versions removed)."""
    version = f"{int(artifact.created_at.timestamp() * 1e6)}-{artifact.size_bytes or 0}"
    folder = cache_dir / "artifacts"
    path = folder / f"{artifact.id}-{version}.h5"
    if path.is_file():
        return path
    with _lock:
        if not path.is_file():
            folder.mkdir(parents=True, exist_ok=True)
            storage.download(artifact.storage_key, path)  # atomic in both backends
            for old in folder.glob(f"{artifact.id}-*"):
                if old != path:
                    old.unlink(missing_ok=True)
    return path


def _orient(name0: str, name1: str) -> tuple[str, str, bool] | None:
    """(aerial, ground, swapped) for an aerial-ground pair, None for any other pair."""
    sets = (_image_set(name0), _image_set(name1))
    if sets == ("aerial", "ground"):
        return name0, name1, False
    if sets == ("ground", "aerial"):
        return name1, name0, True
    return None


def list_pairs(path: str | os.PathLike) -> tuple[str, list[dict[str, Any]]]:
    """(method, aerial-ground pairs with their counts), sorted by aerial then ground name."""
    out = []
    with MatchFile(Path(path)) as mf:
        for group in mf.h5["pairs"].values():
            oriented = _orient(str(group.attrs["name0"]), str(group.attrs["name1"]))
            if oriented is None:
                continue
            inliers = int(group["inliers"][()].sum()) if "inliers" in group else None
            out.append(
                {
                    "aerial": oriented[0],
                    "ground": oriented[1],
                    "num_matches": int(group["matches"].shape[0]),
                    "num_inliers": inliers,
                }
            )
        method = mf.method
    out.sort(key=lambda p: (p["aerial"], p["ground"]))
    return method, out


def read_pair(path: str | os.PathLike, aerial: str, ground: str, inliers_only: bool = False) -> dict | None:
    """One pair's matches as matched keypoint coordinates (aerial first), or None if not in the file."""
    with MatchFile(Path(path)) as mf:
        pm = mf.get_pair(aerial, ground)
        if pm is None:
            return None
        kp_a, kp_g = mf.keypoints(aerial), mf.keypoints(ground)
        size_a, size_g = mf.image_size(aerial), mf.image_size(ground)
        views = mf.views
    m, scores, inl, vidx = pm.matches, pm.scores, pm.inliers, pm.views
    total_inliers = int(inl.sum()) if inl is not None else None
    if inliers_only and inl is not None:
        m, scores, vidx, inl = m[inl], scores[inl], vidx[inl] if vidx is not None else None, inl[inl]
    return {
        "aerial": aerial,
        "ground": ground,
        "num_matches": int(pm.matches.shape[0]),
        "num_inliers": total_inliers,
        "aerial_size": size_a,
        "ground_size": size_g,
        "aerial_xy": kp_a[m[:, 0]].tolist(),
        "ground_xy": kp_g[m[:, 1]].tolist(),
        "scores": scores.astype(float).tolist(),
        "inliers": inl.astype(bool).tolist() if inl is not None else None,
        "views": [views[i] if 0 <= i < len(views) else str(i) for i in vidx.tolist()]
        if vidx is not None
        else None,
    }
