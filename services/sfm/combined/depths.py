"""Ground-ground pairs checked against each other's depths: do their matches put the scene where the
other pairs of the same images put it?

Walking along a street, the windows of a facade repeat along the epipolar lines that the motion draws
(radial from the street's vanishing point): a pair can match each window to the next one along the
street and still fit the true essential matrix, its rotation and baseline direction right to a fraction
of a degree (isprs-walk: three such pairs, 1 of 79, 2 of 23 and 7 of 54 matches correct). Every check of
the relative pose passes them; their points do not: triangulated, they stand 0.47x or 6.5x as deep as
the surface the image sees, and the mapper registers an image on them a street's length off.

The points of a pair are known up to its baseline's length, and a walk's cameras stand nearly on a line,
where the baselines' directions cannot tell their lengths (the POS tells them within metres). Two pairs
that share an image see the same surface at the same pixels: the ratio of their depths there is the
ratio of their baselines' lengths. Each pair's matches are triangulated with a unit baseline; every two
pairs of one image whose matches lie within `radius_px` of each other give the log-ratio of their
lengths (the median over those matches); the lengths are solved from those ratios (a Cauchy loss, so that
a wrong ratio does not drag the others) with the POS lengths as a weak prior. A pair matched along a
repeated facade gets a length its neighbours' ratios agree with but the baselines cannot: the
translation averaging (services.sfm.combined.consistency) then finds its images twice or six times
closer than that length, and refuses it.

    lengths = baseline_lengths(pairs, pos_lengths, K, conf)   # {(a, b): (metres, group)}

Shapes: a pair's keypoints (k, 2) in each image, pixels; its relative pose cam2_from_cam1, R (3, 3) and
t (3,) (any length); K (3, 3) the ground camera's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

Pair = tuple[str, str]

default_conf: dict[str, Any] = {
    "enabled": True,
    "radius_px": 24.0,  # two pairs' matches within this (image pixels) see the same surface ...
    "min_links": 8,  # ... and at least this many such matches tie the two pairs' lengths
    "link_std": 0.1,  # a tie's noise (natural log of the lengths' ratio) for link_reference matches
    "link_reference": 50,
    "loss_scale": 0.2,  # the Cauchy loss's scale on a tie (log ratio)
    "pos_std": 1.0,  # the POS length's prior (log; weak: a walk's POS noise is as long as its baselines)
    "iterations": 10,
}


@dataclass
class PairMatches:
    """A verified pair's inlier keypoints in each image (k, 2) and its relative pose cam2_from_cam1."""

    kp0: np.ndarray
    kp1: np.ndarray
    R: np.ndarray
    t: np.ndarray


def triangulated_depths(
    kp0: np.ndarray, kp1: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The depths (k,) in each camera of matches kp0 <-> kp1 (k, 2) under cam2_from_cam1 (R, t): the
    midpoint of the two rays' closest approach; NaN where the rays are parallel."""
    Ki = np.linalg.inv(K)
    d0 = (Ki @ np.c_[kp0, np.ones(len(kp0))].T).T  # rays in camera 1, z = 1
    d1 = (R.T @ Ki @ np.c_[kp1, np.ones(len(kp1))].T).T  # camera 2's rays in camera 1's frame
    c1 = -R.T @ np.asarray(t, float)  # camera 2's centre in camera 1's frame
    a, b, c = (d0 * d0).sum(1), (d0 * d1).sum(1), (d1 * d1).sum(1)
    e, f = d0 @ c1, d1 @ c1
    den = a * c - b * b
    ok = den > 1e-12 * a * c
    s0 = np.where(ok, (e * c - b * f) / np.where(ok, den, 1.0), np.nan)  # along d0 (its z is 1)
    s1 = np.where(ok, (b * e - a * f) / np.where(ok, den, 1.0), np.nan)  # along d1
    X = 0.5 * (s0[:, None] * d0 + (c1 + s1[:, None] * d1))
    z1 = (X @ R.T + t)[:, 2]
    return X[:, 2], z1


def length_ties(
    pairs: dict[Pair, PairMatches], K: np.ndarray, radius_px: float, min_links: int
) -> list[tuple[Pair, Pair, float, int]]:
    """(p, q, r, n): pairs p and q of one image whose n matches lie within radius_px of each other there,
    r the median log-ratio of q's depth to p's at them (unit baselines): log L_p - log L_q."""
    from scipy.spatial import cKDTree

    per_image: dict[str, list[tuple[Pair, np.ndarray, np.ndarray]]] = {}
    for p, m in pairs.items():
        t = np.asarray(m.t, float)
        z0, z1 = triangulated_depths(
            m.kp0, m.kp1, np.asarray(m.R, float), t / max(float(np.linalg.norm(t)), 1e-12), K
        )
        for name, kp, z in ((p[0], m.kp0, z0), (p[1], m.kp1, z1)):
            ok = np.isfinite(z) & (z > 0)
            if ok.any():
                per_image.setdefault(name, []).append((p, np.asarray(kp, float)[ok], np.log(z[ok])))
    ties = []
    for rows in per_image.values():
        trees = [cKDTree(px) for _, px, _ in rows]
        for i, (p, px, lz) in enumerate(rows):
            for j in range(i + 1, len(rows)):
                q, _, lzq = rows[j]
                near = trees[j].query_ball_point(px, radius_px)
                d = [float(np.median(lzq[idx])) - lz[k] for k, idx in enumerate(near) if idx]
                if len(d) >= min_links:
                    ties.append((p, q, float(np.median(d)), len(d)))
    return ties


def baseline_lengths(
    pairs: dict[Pair, PairMatches],
    pos_lengths: dict[Pair, float],
    K: np.ndarray,
    conf: dict[str, Any] | None = None,
) -> dict[Pair, tuple[float, int]]:
    """The baselines' lengths by pair that fit the ratios their matches' depths give each other (see the
    module), each with its group: the pairs tied to each other, whose lengths are known up to one scale
    (here the one their POS lengths `pos_lengths` give, metres, > 0, weakly; a POS length is biased long
    where its noise is as long as the baseline); empty when off."""
    c = {**default_conf, **(conf or {})}
    names = sorted(p for p in pairs if pos_lengths.get(p, 0.0) > 0)
    if not c["enabled"] or not names:
        return {}
    index = {p: i for i, p in enumerate(names)}
    ties = length_ties({p: pairs[p] for p in names}, K, float(c["radius_px"]), int(c["min_links"]))
    n = len(names)
    prior = np.log([pos_lengths[p] for p in names])
    w_prior = 1.0 / float(c["pos_std"]) ** 2
    log_len = prior.copy()
    for _ in range(max(int(c["iterations"]), 1)):  # Gauss-Newton, each tie reweighted (Cauchy)
        H = np.eye(n) * w_prior
        g = w_prior * prior
        for p, q, r, k in ties:  # log L_p - log L_q = r
            i, j = index[p], index[q]
            e = log_len[i] - log_len[j] - r
            w = min(k, c["link_reference"]) / float(c["link_reference"]) / float(c["link_std"]) ** 2
            w /= 1.0 + (e / float(c["loss_scale"])) ** 2
            H[i, i] += w
            H[j, j] += w
            H[i, j] -= w
            H[j, i] -= w
            g[i] += w * r
            g[j] -= w * r
        new = np.linalg.solve(H, g)
        step, log_len = float(np.abs(new - log_len).max()), new
        if step < 1e-6:
            break
    groups = _groups(ties, index)
    return {p: (float(np.exp(log_len[i])), int(groups[i])) for p, i in index.items()}


def _groups(ties: list[tuple[Pair, Pair, float, int]], index: dict[Pair, int]) -> np.ndarray:
    """Each pair's group (n,): the connected components of the ties."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(index)
    rows = [index[p] for p, _, _, _ in ties]
    cols = [index[q] for _, q, _, _ in ties]
    graph = coo_matrix((np.ones(len(ties)), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]
