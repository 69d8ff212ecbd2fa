"""Steps 3 and 5 of the reducer: the candidate matches of each aerial-ground pair merged over all views
and made one-to-one (deterministic whatever the order of the views), and the pairwise
fundamental-matrix check of what the ground images' poses verified."""

from __future__ import annotations

import numpy as np

from services.reduce.observations import take
from services.reduce.points import Candidates

Pairs = dict[tuple[str, str], dict[str, np.ndarray]]


def merge_one_to_one(cand: dict[str, np.ndarray], view_names: list[str]) -> np.ndarray:
    """Indices into `cand` of the kept correspondences: one per (ia, ig), then one-to-one, greedily in
    the order (score desc, view name, ia, ig). Deterministic and independent of the input order."""
    n = len(cand["ia"])
    if n == 0:
        return np.zeros(0, np.int64)
    vname = np.array([view_names[v] for v in cand["view"]], dtype=object)
    vrank = np.argsort(np.argsort(vname, kind="stable"), kind="stable")  # rank of the view's name
    order = np.lexsort((cand["ig"], cand["ia"], vrank, -cand["score"].astype(np.float64)))
    used_a: set[int] = set()
    used_g: set[int] = set()
    keep = []
    for k in order:
        a, g = int(cand["ia"][k]), int(cand["ig"][k])
        if a in used_a or g in used_g:
            continue
        used_a.add(a)
        used_g.add(g)
        keep.append(int(k))
    return np.array(keep, np.int64)


def merge_candidates(cands: Candidates, view_names: list[str]) -> Pairs:
    """Per pair, the candidates as arrays (ia, ig, score, view, X, n_aerial), one-to-one
    (merge_one_to_one)."""
    merged: Pairs = {}
    for key in sorted(cands):
        rows = cands[key]
        c = {
            "ia": np.array([r["ia"] for r in rows], np.int64),
            "ig": np.array([r["ig"] for r in rows], np.int64),
            "score": np.array([r["score"] for r in rows], np.float32),
            "view": np.array([r["view"] for r in rows], np.int64),
            "X": np.array([r["X"] for r in rows], float).reshape(-1, 3),
            "n_aerial": np.array([r["n_aerial"] for r in rows], np.int64),
        }
        merged[key] = take(c, merge_one_to_one(c, view_names))
    return merged


def verify_pairs(
    merged: Pairs, verified: dict[tuple[str, str], np.ndarray], keypoints: dict[str, np.ndarray], conf: dict
) -> Pairs:
    """The reducer's output pairs: each pair's matches (M, 2), scores, views, X and inliers, the matches
    that the pose check verified and then a fundamental-matrix RANSAC (pairs with >= 8 of them) kept;
    pairs left with fewer than min_pair_matches get no inliers."""
    from services.matching import verify_fundamental

    fc = conf["fundamental"]
    f_conf = {"threshold": fc["threshold"], "confidence": fc["confidence"], "max_iters": fc["max_iters"]}
    pairs = {}
    for key in sorted(merged):
        a, g = key
        m = merged[key]
        inl = verified[key]
        if fc["enabled"] and inl.sum() >= 8:
            mm = np.stack([m["ia"][inl], m["ig"][inl]], 1)
            f_inl = verify_fundamental(keypoints[a], keypoints[g], mm, f_conf)
            inl = inl.copy()
            inl[np.flatnonzero(inl)] = f_inl
        if inl.sum() < conf["min_pair_matches"]:
            inl = np.zeros_like(inl)
        pairs[key] = {
            "matches": np.stack([m["ia"], m["ig"]], 1).astype(np.int32).reshape(-1, 2),
            "scores": m["score"].astype(np.float32),
            "inliers": inl,
            "views": m["view"].astype(np.int32),
            "X": m["X"],
        }
    return pairs
