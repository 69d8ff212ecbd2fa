"""Ground-ground pairs checked against each other: do their baselines agree on where the cameras stand?

A pair of images of two walls that carry the same texture (repeated facades, shop fronts) can pass the
essential matrix, the POS (whose noise on the ground, metres, is as large as the baselines of a walk)
and, where neither image is tied to the aerial images, every check of one pair alone. The other pairs
can tell: each verified pair gives the direction of its baseline (the essential matrix's, from its first
image's centre to its second's, turned into the model's frame by the first image's attitude), and where
a walk captures the street densely the directions of the others fix where its images stand relative to
each other far better than their POS. On `isprs-walk` the three verified pairs without a correct match
point 108-175 degrees away from the truth, the true ones within 11 (docs/measurements.md).

The images' centres are solved from every pair's direction, each baseline with a positive length
(C_b - C_a = lambda u, lambda >= 0: the order of the images along a street is the pairs', not the POS's),
and the POS centres as a weak prior (their noise; the reducer's aerial-tied poses where it has them): a
translation averaging, by bounded least squares (scipy's lsq_linear), reweighted a few times with a
Cauchy loss on each pair's angle so that a wrong pair does not drag the others. A pair whose direction
then stands more than `max_angle_deg` from the baseline the solution puts between its images is refused.
A pair nothing else constrains (a bridge between two parts) is what the solution follows: kept.
Where the pairs' matches' depths give their baselines' lengths (services.sfm.combined.depths: on a walk
the cameras stand nearly on a line, where the directions cannot tell lengths), the solution fits those
too, each group of them up to a scale of its own, and a pair whose length disagrees with where the
others put its images (a repeated facade matched along the street, its relative pose true) is refused.

    refused = inconsistent_pairs(directions, priors, prior_std, conf)   # {(a, b): reason}

Shapes: a pair's direction (3,), the unit vector from its first image's centre to its second's in the
model's frame; centres (n, 3).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from services.colmap_model import Pose

Pair = tuple[str, str]
PosStd = tuple[float, float, float]  # (horizontal m, vertical m, attitude deg)

default_conf: dict[str, Any] = {
    "enabled": True,
    # a pair's baseline direction: the essential matrix's error (up to 11 degrees on isprs-walk's short
    # baselines) and its first image's POS attitude, which turns it into the model's frame
    "direction_std_deg": 5.0,
    "reference_inliers": 100,  # ... for a pair of this many verified matches
    "max_angle_deg": 30.0,  # a pair whose direction stands farther off the solution's baseline: refused
    # a baseline is at least this long (metres) and this share of its POS length: with no floor, noisy
    # directions pull images together until their baselines can point anywhere
    "min_length_m": 1.0,
    "min_length_share": 0.25,
    "max_refused": 50,  # pairs refused one by one (the worst, then the others solved again) at most
    # with the lengths its matches' depths give a baseline (services.sfm.combined.depths): their noise,
    # as a share of the length, and the factor beyond which a pair's length and where the solution puts
    # its images disagree
    "length_std_share": 0.15,
    "max_length_ratio": 1.6,
}


def pair_direction(R: np.ndarray, t: np.ndarray, first: Pose) -> np.ndarray:
    """The unit direction (3,) in the model's frame from the first image's centre to the second's, of an
    essential matrix's relative pose cam2_from_cam1 (R (3, 3), t (3,)), turned by the first image's
    attitude `first` (cam_from_world)."""
    d = first.R.T @ (-R.T @ np.asarray(t, float))
    return d / max(float(np.linalg.norm(d)), 1e-12)


def solve_centres(
    directions: dict[Pair, np.ndarray],
    weights: dict[Pair, float],
    min_lengths: dict[Pair, float],
    prior: dict[str, np.ndarray],
    prior_std: dict[str, tuple[float, float]],
    lengths: dict[Pair, tuple[float, float, int]] | None = None,
) -> tuple[dict[str, np.ndarray], dict[int, float]]:
    """The centres (3,) by name that best fit every pair's direction with a baseline of at least its
    `min_lengths` (metres; each pair's rows weighted by `weights`), the baselines' relative `lengths`
    where given ((length, its std, its group): the lengths their matches' depths give, each group's
    known up to one scale, services.sfm.combined.depths) and the prior centres with their (horizontal,
    vertical) noise; and each group's scale."""
    from scipy.optimize import lsq_linear
    from scipy.sparse import coo_matrix

    names = sorted(prior)
    index = {n: i for i, n in enumerate(names)}
    groups = {g: i for i, g in enumerate(sorted({g for _, _, g in (lengths or {}).values()}))}
    n, m = len(names), len(directions)
    origin = np.mean([prior[x] for x in names], axis=0)
    rows, cols, vals, rhs = [], [], [], []
    r = 0
    for e, ((a, b), u) in enumerate(directions.items()):
        s = math.sqrt(weights[(a, b)])
        for k in range(3):  # s (C_b - C_a - lambda u)_k = 0
            rows += [r, r, r]
            cols += [3 * index[b] + k, 3 * index[a] + k, 3 * n + e]
            vals += [s, -s, -s * float(u[k])]
            rhs.append(0.0)
            r += 1
        if (a, b) in (lengths or {}):  # (lambda - g L) / sd = 0
            length, sd, g = (lengths or {})[(a, b)]
            rows += [r, r]
            cols += [3 * n + e, 3 * n + m + groups[g]]
            vals += [1.0 / sd, -length / sd]
            rhs.append(0.0)
            r += 1
    for x in names:
        h, v = prior_std[x]
        for k, sd in enumerate((h, h, v)):  # (C - P)_k / sd = 0
            rows.append(r)
            cols.append(3 * index[x] + k)
            vals.append(1.0 / sd)
            rhs.append(float(prior[x][k] - origin[k]) / sd)
            r += 1
    size = 3 * n + m + len(groups)
    A = coo_matrix((vals, (rows, cols)), shape=(r, size)).tocsr()
    lower = np.r_[np.full(3 * n, -np.inf), [min_lengths[p] for p in directions], np.full(len(groups), 1e-3)]
    sol = lsq_linear(A, np.asarray(rhs), bounds=(lower, np.full(size, np.inf)), lsmr_tol="auto")
    C = sol.x[: 3 * n].reshape(n, 3) + origin
    return {x: C[i] for x, i in index.items()}, {g: float(sol.x[3 * n + m + i]) for g, i in groups.items()}


def pair_angles(directions: dict[Pair, np.ndarray], centres: dict[str, np.ndarray]) -> dict[Pair, float]:
    """Each pair's direction against the baseline between its images' centres, in degrees (0-180)."""
    out = {}
    for (a, b), u in directions.items():
        D = centres[b] - centres[a]
        c = float(D @ u) / max(float(np.linalg.norm(D)), 1e-12)
        out[(a, b)] = math.degrees(math.acos(min(max(c, -1.0), 1.0)))
    return out


def inconsistent_pairs(
    directions: dict[Pair, np.ndarray],
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
    conf: dict[str, Any] | None = None,
    anchors: dict[str, tuple[Pose, PosStd]] | None = None,
    inliers: dict[Pair, int] | None = None,
    lengths: dict[Pair, tuple[float, int]] | None = None,
) -> dict[Pair, str]:
    """The pairs refused by the others (see the module): {pair: reason}. `directions` maps each pair
    to its baseline's unit direction in the model's frame (pair_direction); `priors` and `prior_std` are
    the images' POS poses and noise, `anchors` poses tied to the aerial images that replace them and
    `inliers` each pair's verified matches (a direction's noise shrinks with their square root). With
    `lengths` ((length, group): the lengths the pairs' matches' depths give their baselines, each group's
    up to one scale, services.sfm.combined.depths.baseline_lengths) the solution fits them too (within
    `length_std_share`), and a pair whose images it puts more than `max_length_ratio` times farther apart
    or closer than its scaled length is refused as well."""
    c = {**default_conf, **(conf or {})}
    if not c["enabled"] or len(directions) < 2:
        return {}
    prior, std = {}, {}
    for x in sorted({n for p in directions for n in p}):
        pose, s = (anchors or {}).get(x) or (priors[x], prior_std[x])
        prior[x], std[x] = pose.center, (float(s[0]), float(s[1]))
    sigma = math.radians(float(c["direction_std_deg"]))
    base, shortest = {}, {}
    for a, b in directions:
        length = max(float(np.linalg.norm(prior[b] - prior[a])), float(c["min_length_m"]))
        share = (inliers or {}).get((a, b), c["reference_inliers"]) / float(c["reference_inliers"])
        base[(a, b)] = share / (sigma * length) ** 2
        shortest[(a, b)] = max(float(c["min_length_share"]) * length, float(c["min_length_m"]))
    dirs, out = dict(directions), {}
    limit = float(c["max_angle_deg"])
    share = float(c["length_std_share"])
    lens = {p: (L, share * L, g) for p, (L, g) in (lengths or {}).items() if p in dirs and L > 0}
    log_limit = math.log(float(c["max_length_ratio"]))
    while len(out) < int(c["max_refused"]):
        centres, scales = solve_centres(dirs, base, shortest, prior, std, lens)
        if len(dirs) < 2:
            break
        angles = pair_angles(dirs, centres)
        ratios = {
            p: float(np.linalg.norm(centres[p[1]] - centres[p[0]])) / (L * scales[g])
            for p, (L, _, g) in lens.items()
        }
        score = {
            p: max(angles[p] / limit, abs(math.log(max(ratios.get(p, 1.0), 1e-9))) / log_limit) for p in dirs
        }
        worst = max(score, key=lambda p: score[p])
        if score[worst] <= 1.0:
            break
        if angles[worst] > limit:
            out[worst] = (
                f"its baseline stands {angles[worst]:.0f} deg from where the other pairs and the POS put "
                f"its images (> {limit:.0f})"
            )
        else:
            out[worst] = (
                f"its matches' depths make its baseline {1.0 / ratios[worst]:.2f}x as long as where the "
                f"other pairs and the POS put its images (beyond {c['max_length_ratio']:.1f}x either way: "
                "a repeated facade matched along the street)"
            )
        dirs.pop(worst)
        lens.pop(worst, None)
    return out
