"""The ground-ground pairs' putative matches, kept beside the feature cache (services.sfm.combined).

Matching the ground pairs (LightGlue on the CPU: about a second a pair on 2 cores) is most of the combined
SfM's database step, and the same pairs come back whenever the combined SfM runs again on the same
features: a stage rerun after the reducer, the demo's ALIKED+LightGlue baseline through the same procedure.
One HDF5 file per matcher conf beside the feature file holds each pair's matches with a digest of both
images' features, so a pair is matched again only when its features changed.

    matches = match_ground_pairs(feats, pairs, matcher_conf, pair_cache_path(feature_path, matcher_conf))
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

logger = logging.getLogger("midview.combined_sfm")

Features = dict[str, np.ndarray]
Pair = tuple[str, str]


def pair_cache_path(feature_path: str | Path, matcher_conf: dict[str, Any]) -> Path:
    """The cache file of `matcher_conf`'s matches of the features in `feature_path`."""
    key = hashlib.sha256(json.dumps(matcher_conf, sort_keys=True).encode()).hexdigest()[:12]
    p = Path(feature_path)
    return p.with_name(f"{p.stem}.ground-pairs-{key}.h5")


def features_digest(f0: Features, f1: Features) -> str:
    """A digest of two images' keypoints and descriptors (what their matches depend on)."""
    h = hashlib.sha256()
    for f in (f0, f1):
        for k in ("keypoints", "descriptors"):
            a = np.ascontiguousarray(f[k])
            h.update(f"{k}{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


def _key(pair: Pair) -> str:
    return f"{pair[0]}|{pair[1]}".replace("/", "\\")  # HDF5 names: no group separators


def read_cached(path: Path, wanted: dict[Pair, str]) -> dict[Pair, np.ndarray]:
    """The cached matches (M, 2) of the pairs of `wanted` ({pair: features_digest}) whose digest agrees;
    nothing from a missing or unreadable file."""
    out: dict[Pair, np.ndarray] = {}
    if not path.is_file():
        return out
    try:
        with h5py.File(path, "r") as f:
            for pair, digest in wanted.items():
                d = f.get(_key(pair))
                if d is not None and d.attrs.get("features") == digest:
                    out[pair] = np.asarray(d[()], np.int64).reshape(-1, 2)
    except OSError as e:  # a torn or foreign file: match again, and the write replaces it
        logger.warning("ground pairs' match cache %s unreadable (%s): matching again", path, e)
        return {}
    return out


def write_cached(path: Path, new: dict[Pair, tuple[np.ndarray, str]]) -> None:
    """Add `new` ({pair: (matches, features digest)}) to the cache: the old entries copied into a new file
    that replaces it atomically (a reader keeps the file it opened)."""
    if not new:
        return
    tmp = path.with_name(f"{path.name}.{os.getpid()}.part")
    with h5py.File(tmp, "w") as out:
        if path.is_file():
            try:
                with h5py.File(path, "r") as old:
                    for k in old:
                        old.copy(old[k], out, name=k)
            except OSError:
                pass  # an unreadable old cache is dropped
        for pair, (m, digest) in new.items():
            k = _key(pair)
            if k in out:
                del out[k]
            d = out.create_dataset(k, data=np.asarray(m, np.int32).reshape(-1, 2))
            d.attrs["features"] = digest
    os.replace(tmp, path)


def match_ground_pairs(
    feats: dict[str, Features],
    pairs: list[Pair],
    matcher_conf: dict[str, Any],
    cache: Path | None,
    match: Callable[[Features, Features, dict[str, Any]], tuple[np.ndarray, np.ndarray]] | None = None,
    prog: Callable[[float, str], None] | None = None,
) -> dict[Pair, np.ndarray]:
    """Each pair's putative matches (M, 2) from `match` (services.matching.match_features), read from
    `cache` where it holds them for the same features, the others matched and added to it."""
    if match is None:
        from services.matching import match_features as match
    digests = {p: features_digest(feats[p[0]], feats[p[1]]) for p in pairs}
    out = read_cached(cache, digests) if cache is not None else {}
    todo = [p for p in pairs if p not in out]
    new: dict[Pair, tuple[np.ndarray, str]] = {}
    for i, p in enumerate(todo):
        m, _ = match(feats[p[0]], feats[p[1]], matcher_conf)
        out[p] = np.asarray(m, np.int64).reshape(-1, 2)
        new[p] = (out[p], digests[p])
        if prog is not None:
            prog((i + 1) / len(todo), f"ground pair {i + 1}/{len(todo)} matched")
    if cache is not None:
        write_cached(cache, new)
    if pairs:
        logger.info(
            "ground pairs: %d matched, %d from the cache %s", len(todo), len(pairs) - len(todo), cache
        )
    return out
