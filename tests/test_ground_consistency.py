"""Ground-ground pairs checked against each other's baselines (services.sfm.combined.consistency)."""

from __future__ import annotations

import numpy as np
import pytest

from services.colmap_model import Pose
from services.geometry import angle_deg, look_at
from services.sfm.combined.consistency import inconsistent_pairs, pair_direction

STD = (2.5, 4.0, 2.0)  # phone GNSS in a street canyon (the isprs presets' ground POS)


def _walk(n: int, step: float = 3.5) -> dict[str, Pose]:
    """n cameras 3.5 m apart along a straight street, each looking at the facade across it."""
    poses = {}
    for i in range(n):
        c = np.array([step * i, 0.0, 1.7])
        poses[f"ground/G{i:04d}.jpg"] = look_at(c, c + np.array([1.0, 12.0, 3.0]))
    return poses


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _survey(poses: dict[str, Pose], reach: int, noise_deg: float, seed: int):
    """Each image paired with its next `reach` images: their baselines' directions with `noise_deg` of
    noise, and POS centres with STD's noise."""
    rng = np.random.default_rng(seed)
    names = sorted(poses)
    dirs = {}
    for i, a in enumerate(names):
        for b in names[i + 1 : i + 1 + reach]:
            d = _unit(poses[b].center - poses[a].center) + rng.normal(0, np.radians(noise_deg), 3)
            dirs[(a, b)] = _unit(d)
    priors = {
        n: Pose.from_center(p.R.T, p.center + rng.normal(0, 1, 3) * [STD[0], STD[0], STD[1]])
        for n, p in poses.items()
    }
    return dirs, priors, {n: STD for n in poses}


def test_pair_direction_of_an_essential_matrix():
    poses = _walk(3)
    a, b = poses["ground/G0000.jpg"], poses["ground/G0002.jpg"]
    R = b.R @ a.R.T
    t = b.t - R @ a.t
    d = pair_direction(R, 5.0 * t / np.linalg.norm(t), a)
    assert angle_deg(d, b.center - a.center) < 1e-6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_true_pairs_of_a_walk_are_kept(seed):
    dirs, priors, std = _survey(_walk(14), 3, 1.5, seed)
    assert inconsistent_pairs(dirs, priors, std) == {}


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("turn_deg", [180.0, 110.0])
def test_a_pair_of_a_repeated_facade_is_refused(seed, turn_deg):
    """G0005-G0007 matched a facade repeated along the street: its essential matrix points back along the
    walk (isprs-walk's false pairs: 170-175 degrees) or across it (108 degrees). The POS (2.5 m noise,
    7 m apart) cannot tell, the walk's other pairs can."""
    poses = _walk(14)
    dirs, priors, std = _survey(poses, 3, 1.5, seed)
    a, b = "ground/G0005.jpg", "ground/G0007.jpg"
    true = _unit(poses[b].center - poses[a].center)
    t = np.radians(turn_deg)
    dirs[(a, b)] = np.array([np.cos(t), 0.0, np.sin(t)]) if true[0] > 0 else -true
    # its matches: fewer than its true neighbours' (isprs-walk: 24-99 against 90-494), so that where
    # it contradicts two of them (G0005-G0006-G0007) the solution takes their word, not its
    inliers = {p: 300 for p in dirs} | {(a, b): 80}
    refused = inconsistent_pairs(dirs, priors, std, inliers=inliers)
    assert list(refused) == [(a, b)], refused
    assert "from where the other pairs" in refused[(a, b)]


def test_a_pair_the_others_do_not_determine_is_kept():
    """Two walks joined by one short pair: a wrong direction on that bridge has nothing to disagree with
    but the POS, whose noise is as large as the bridge: the solution follows it."""
    left, right = _walk(6), _walk(6)
    poses = dict(left)
    for i, (_, p) in enumerate(sorted(right.items())):
        c = p.center + [21.0, 1.0, 0.0]  # the second walk goes on 3.6 m after the first
        poses[f"ground/H{i:04d}.jpg"] = look_at(c, c + np.array([1.0, 12.0, 3.0]))
    dirs, priors, std = _survey(left, 2, 1.0, 0)
    d2, p2, s2 = _survey({n: p for n, p in poses.items() if "/H" in n}, 2, 1.0, 1)
    dirs.update(d2)
    priors.update(p2)
    std.update(s2)
    a, b = "ground/G0005.jpg", "ground/H0000.jpg"
    true = _unit(poses[b].center - poses[a].center)
    dirs[(a, b)] = -true  # reversed
    assert inconsistent_pairs(dirs, priors, std) == {}


def test_an_aerial_tied_anchor_sharpens_the_check():
    """Anchors (the reducer's PnP poses, 0.1 m) replace the POS of their images."""
    poses = _walk(8)
    dirs, priors, std = _survey(poses, 2, 1.0, 3)
    anchors = {n: (p, (0.1, 0.1, 0.2)) for n, p in poses.items() if n.endswith(("0.jpg", "3.jpg", "6.jpg"))}
    assert inconsistent_pairs(dirs, priors, std, anchors=anchors) == {}
