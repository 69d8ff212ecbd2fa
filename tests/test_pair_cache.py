"""The ground pairs' match cache (services.sfm.combined.pair_cache): a pair is matched once for the same
features and matcher conf, again when either image's features changed; a torn cache is matched again."""

from __future__ import annotations

import numpy as np

from services.sfm.combined.pair_cache import match_ground_pairs, pair_cache_path

CONF = {"name": "nn-ratio", "ratio": 0.8}


def _feats(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "keypoints": rng.uniform(0, 500, (40, 2)).astype(np.float32),
        "descriptors": rng.normal(size=(40, 8)).astype(np.float32),
    }


class CountingMatcher:
    """Matches keypoint i to i for the first n = (a's seed + b's seed) % 7 + 3 keypoints; counts calls."""

    def __init__(self) -> None:
        self.calls: list[tuple[float, float]] = []

    def __call__(self, f0, f1, conf):
        self.calls.append((float(f0["keypoints"][0, 0]), float(f1["keypoints"][0, 0])))
        n = int(f0["keypoints"][0, 0] + f1["keypoints"][0, 0]) % 7 + 3
        return np.stack([np.arange(n), np.arange(n)], 1), np.ones(n)


def test_pairs_are_matched_once_for_the_same_features(tmp_path):
    feats = {f"ground/G{i}.jpg": _feats(i) for i in range(4)}
    pairs = [
        ("ground/G0.jpg", "ground/G1.jpg"),
        ("ground/G1.jpg", "ground/G2.jpg"),
        ("ground/G2.jpg", "ground/G3.jpg"),
    ]
    cache = pair_cache_path(tmp_path / "feats.h5", CONF)
    m = CountingMatcher()
    first = match_ground_pairs(feats, pairs, CONF, cache, match=m)
    assert len(m.calls) == 3 and cache.is_file()
    again = match_ground_pairs(feats, pairs, CONF, cache, match=m)
    assert len(m.calls) == 3  # all from the cache
    for p in pairs:
        np.testing.assert_array_equal(again[p], first[p])
    # one image's features changed: only its pairs are matched again
    feats["ground/G3.jpg"] = _feats(33)
    match_ground_pairs(feats, pairs, CONF, cache, match=m)
    assert len(m.calls) == 4
    # another matcher conf has a cache of its own
    assert pair_cache_path(tmp_path / "feats.h5", {**CONF, "ratio": 0.9}) != cache


def test_a_torn_cache_is_matched_again_and_replaced(tmp_path):
    feats = {f"ground/G{i}.jpg": _feats(i) for i in range(2)}
    pairs = [("ground/G0.jpg", "ground/G1.jpg")]
    cache = pair_cache_path(tmp_path / "feats.h5", CONF)
    cache.write_bytes(b"not an HDF5 file")
    m = CountingMatcher()
    out = match_ground_pairs(feats, pairs, CONF, cache, match=m)
    assert len(m.calls) == 1 and len(out[pairs[0]]) >= 3
    match_ground_pairs(feats, pairs, CONF, cache, match=m)
    assert len(m.calls) == 1  # the replaced cache is read
    assert not list(tmp_path.glob("*.part"))
