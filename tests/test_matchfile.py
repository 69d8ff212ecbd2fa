"""The common match file."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from shared.matchfile import MatchFile, PairMatches


def test_round_trip_and_orientation(tmp_path):
    path = tmp_path / "m.h5"
    k0 = np.random.default_rng(0).uniform(0, 100, (10, 2)).astype(np.float32)
    k1 = np.random.default_rng(1).uniform(0, 100, (7, 2)).astype(np.float32)
    m = np.array([[0, 3], [5, 6], [9, 0]])
    with MatchFile(path, "w", method="test") as mf:
        mf.add_keypoints("aerial/A.jpg", k0, (100, 80))
        mf.add_keypoints("ground/G.jpg", k1, (64, 48))
        v = mf.view_index("render/V1")
        mf.add_pair(
            PairMatches("ground/G.jpg", "aerial/A.jpg", m[:, ::-1], np.ones(3), np.array([1, 0, 1]), [v] * 3)
        )
    with MatchFile(path) as mf:
        assert mf.method == "test"
        assert mf.image_names() == ["aerial/A.jpg", "ground/G.jpg"]
        assert mf.image_size("ground/G.jpg") == (64, 48)
        np.testing.assert_array_equal(mf.keypoints("aerial/A.jpg"), k0)
        pm = mf.get_pair("aerial/A.jpg", "ground/G.jpg")
        np.testing.assert_array_equal(pm.matches, m)
        assert pm.inliers.tolist() == [True, False, True]
        assert mf.views == ["render/V1"] and pm.views.tolist() == [0, 0, 0]
        assert mf.get_pair("aerial/A.jpg", "ground/X.jpg") is None
        assert len(list(mf.iter_pairs())) == 1


def test_rejects_other_files_and_orphan_pairs(tmp_path):
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(ValueError, match="not a midview match file"):
        MatchFile(tmp_path / "other.h5")
    with MatchFile(tmp_path / "m.h5", "w") as mf, pytest.raises(KeyError, match="add keypoints"):
        mf.add_pair(PairMatches("a/1.jpg", "b/2.jpg", np.zeros((0, 2)), np.zeros(0)))
