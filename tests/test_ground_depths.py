"""Ground-ground pairs checked against each other's depths (services.sfm.combined.depths, with the
baselines' lengths in services.sfm.combined.consistency)."""

from __future__ import annotations

import numpy as np
import pytest

from services.colmap_model import Pose
from services.geometry import look_at
from services.sfm.combined.consistency import inconsistent_pairs, pair_direction
from services.sfm.combined.depths import PairMatches, baseline_lengths, triangulated_depths

K = np.array([[750.0, 0.0, 512.0], [0.0, 750.0, 384.0], [0.0, 0.0, 1.0]])
STD = (2.5, 4.0, 2.0)  # phone GNSS in a street canyon (the isprs presets' ground POS)


def _walk(n: int, step: float = 3.5) -> dict[str, Pose]:
    """n cameras 3.5 m apart along a straight street (x), each looking at the facade across it (y = 12)."""
    poses = {}
    for i in range(n):
        c = np.array([step * i, 0.0, 1.7])
        poses[f"ground/G{i:04d}.jpg"] = look_at(c, c + np.array([2.0, 12.0, 3.0]))
    return poses


def _project(pose: Pose, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (n, 2) of points X (n, 3) and whether each is in front and within the 1024 x 768 image."""
    x = (pose.R @ X.T).T + pose.t
    uv = (K @ x.T).T
    px = uv[:, :2] / uv[:, 2:3]
    ok = (x[:, 2] > 0.1) & (px[:, 0] >= 0) & (px[:, 0] < 1024) & (px[:, 1] >= 0) & (px[:, 1] < 768)
    return px, ok


def _facade(rng: np.random.Generator, length: float) -> np.ndarray:
    """Points (n, 3) on the facade across the street (y = 12, 0-10 m high)."""
    n = int(60 * length)
    return np.c_[rng.uniform(-5.0, length + 5.0, n), np.full(n, 12.0), rng.uniform(0.0, 10.0, n)]


def _pair(a: Pose, b: Pose, X: np.ndarray, slide: float = 1.0) -> PairMatches:
    """The matches of a and b on points X; with `slide` != 1 each of a's pixels is matched in b to the
    point `slide` times as deep along a's ray (a repeated facade matched along the epipolar lines)."""
    pa, oka = _project(a, X)
    Xb = a.center + slide * (X - a.center)
    pb, okb = _project(b, Xb)
    ok = oka & okb
    R = b.R @ a.R.T
    return PairMatches(pa[ok], pb[ok], R, b.t - R @ a.t)


def _survey(slide: dict[tuple[int, int], float], seed: int):
    """A walk of 12 images, each paired with its next 3; the pairs in `slide` matched along the street."""
    rng = np.random.default_rng(seed)
    poses = _walk(12)
    names = sorted(poses)
    X = _facade(rng, 3.5 * 12)
    pairs = {}
    for i, a in enumerate(names):
        for j in range(i + 1, min(i + 4, len(names))):
            m = _pair(poses[a], poses[names[j]], X, slide.get((i, j), 1.0))
            if len(m.kp0) >= 15:
                pairs[(a, names[j])] = m
    priors = {
        n: Pose.from_center(p.R.T, p.center + rng.normal(0, 1, 3) * [STD[0], STD[0], STD[1]])
        for n, p in poses.items()
    }
    return poses, pairs, priors


def _refused(poses, pairs, priors, with_depths: bool) -> set[tuple[str, str]]:
    dirs = {p: pair_direction(m.R, m.t, poses[p[0]]) for p, m in pairs.items()}
    pos = {(a, b): float(np.linalg.norm(priors[b].center - priors[a].center)) for a, b in pairs}
    lengths = baseline_lengths(pairs, pos, K) if with_depths else None
    sizes = {p: len(m.kp0) for p, m in pairs.items()}
    std = {n: STD for n in priors}
    return set(inconsistent_pairs(dirs, priors, std, None, None, sizes, lengths))


def test_triangulated_depths_are_the_points_depths():
    rng = np.random.default_rng(0)
    a, b = _walk(3)["ground/G0000.jpg"], _walk(3)["ground/G0002.jpg"]
    X = _facade(rng, 7.0)
    m = _pair(a, b, X)
    z0, z1 = triangulated_depths(m.kp0, m.kp1, m.R, m.t, K)
    pa, oka = _project(a, X)
    _, okb = _project(b, X)
    ok = oka & okb
    assert np.allclose(z0, ((a.R @ X[ok].T).T + a.t)[:, 2], rtol=1e-6)
    assert np.allclose(z1, ((b.R @ X[ok].T).T + b.t)[:, 2], rtol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_true_pairs_of_a_walk_are_kept(seed):
    poses, pairs, priors = _survey({}, seed)
    assert _refused(poses, pairs, priors, True) == set()


@pytest.mark.parametrize(("slide", "seed"), [(0.47, 0), (0.47, 1), (2.5, 0), (2.5, 2)])
def test_a_pair_matched_along_a_repeated_facade_is_refused(slide, seed):
    """Matched at 0.47x or 2.5x the true depth along the epipolar lines (isprs-walk: 0.47x, 6.5x), its
    relative pose true: the baselines' directions alone keep it, their lengths do not."""
    poses, pairs, priors = _survey({(4, 6): slide}, seed)
    wrong = (sorted(poses)[4], sorted(poses)[6])
    assert wrong in pairs
    assert _refused(poses, pairs, priors, False) == set()
    assert _refused(poses, pairs, priors, True) == {wrong}


def test_lengths_follow_the_depths_not_the_pos():
    """The lengths' ratios within a group are the depths', whatever the POS's noise."""
    poses, pairs, priors = _survey({}, 3)
    pos = {(a, b): float(np.linalg.norm(priors[b].center - priors[a].center)) for a, b in pairs}
    lengths = baseline_lengths(pairs, pos, K)
    assert len({g for _, g in lengths.values()}) == 1
    ratio = [L / np.linalg.norm(poses[b].center - poses[a].center) for (a, b), (L, _) in lengths.items()]
    assert np.ptp(np.log(ratio)) < 0.01
