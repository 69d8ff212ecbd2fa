"""Learned tracks across the aerial images (services.views.tracks) on the analytic survey of
tests/test_view_stereo.py (a textured ground plane with a raised platform, six nadir images of two flight
lines flown in opposite directions): the points triangulated on the known poses lie on the true surface,
far more of them than the sparse model holds, and a match off its epipolar line is not kept."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from services.colmap_model import Pose
from services.views.tracks import cached, covisible_pairs, epipolar_inliers
from tests.test_view_stereo import PLATFORM, survey  # noqa: F401  (the module's fixture)


def _true_height(P: np.ndarray) -> np.ndarray:
    x0, x1, y0, y1, h = PLATFORM
    on = (P[:, 0] >= x0) & (P[:, 0] <= x1) & (P[:, 1] >= y0) & (P[:, 1] <= y1)
    return np.where(on, h, 0.0)


@pytest.mark.parametrize("matcher", ["epipolar", "lightglue"])
def test_tracks_lie_on_the_true_surface_and_outnumber_the_sparse_points(survey, tmp_path, matcher):  # noqa: F811
    root, _ = survey
    conf = {"resize_max": 640, "max_keypoints": 1024, "partners": 3, "min_shared": 20, "voxel_m": 0.05}
    conf["matcher"] = matcher
    P = cached(root / "sparse", root / "images", conf, tmp_path)
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    assert len(P) > 2 * rec.num_points3D()
    dz = np.abs(P[:, 2] - _true_height(P))
    # the cameras fly 40 m up: 1% of their depth is 0.4 m
    assert np.median(dz) < 0.05 and np.mean(dz < 0.4) > 0.95
    assert (P[:, 2] > 2.5).sum() > 50  # the platform has points of its own
    again = cached(root / "sparse", root / "images", conf, tmp_path)  # read back, not recomputed
    assert np.array_equal(P, again) and len(list(tmp_path.glob("tracks-*.npy"))) == 1


def test_pairs_are_each_images_most_covisible_partners(survey):  # noqa: F811
    root, _ = survey
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    pairs = covisible_pairs(rec, 1, 20)
    assert pairs and all(a < b for a, b in pairs)
    assert {i for p in pairs for i in p} == set(rec.images)


def test_a_match_off_its_epipolar_line_is_not_kept(survey):  # noqa: F811
    root, cam = survey
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    a, b = 1, 2
    pa, pb = Pose.of_image(rec.images[a]), Pose.of_image(rec.images[b])
    X = np.array([[1.0, -2.0, 0.0], [3.0, 1.0, 5.0]])
    ua, _ = pa.project(cam.K, X)
    ub, _ = pb.project(cam.K, X)
    c = rec.cameras[1]
    assert epipolar_inliers(c, pa, ua, c, pb, ub, 1.0).all()
    # moved along the flight line (the epipolar direction here) a match stays; across it, it goes
    moved = ub + np.array([[0.0, 5.0], [0.0, 5.0]])
    assert not epipolar_inliers(c, pa, ua, c, pb, moved, 1.0).any()
