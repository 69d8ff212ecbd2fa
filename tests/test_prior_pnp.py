"""PnP whose hypotheses must agree with the POS (services.reduce.prior_pnp) and the reducer's use of it: a
ground image whose true pose is outvoted by a repeated facade is still localized, at the true pose."""

from __future__ import annotations

import copy

import cv2
import numpy as np

from services import reduce as transfer
from services.colmap_model import Camera, Pose
from services.geometry import look_at
from services.reduce.prior_pnp import (
    distinct_triples,
    inlier_counts,
    p3p_many,
    prior_gated_pnp,
    reprojection_errors,
    rotations,
)

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
TRUE = look_at(np.array([0.0, 0.0, 1.6]), np.array([0.0, 20.0, 4.0]))
WRONG = look_at(np.array([40.0, 5.0, 1.6]), np.array([40.0, 25.0, 4.0]))  # 40 m along the street
STD = (2.5, 4.0, 2.0)


def _correspondences(seed: int = 0, n_true: int = 40, n_wrong: int = 90):
    """n_true keypoints spread over the image with their true points, and n_wrong keypoints whose
    points fit WRONG (a facade 40 m further that looks the same): the most inliers belong to WRONG."""
    rng = np.random.default_rng(seed)

    def pts(pose, n):
        kp = np.stack([rng.uniform(40, 984, n), rng.uniform(40, 728, n)], 1)
        return kp, pose.unproject(CAM.K, kp, rng.uniform(8.0, 35.0, n))

    kp_t, X_t = pts(TRUE, n_true)
    kp_w, X_w = pts(WRONG, n_wrong)
    kp = np.concatenate([kp_t, kp_w]) + rng.normal(0, 0.3, (n_true + n_wrong, 2))
    return kp, np.concatenate([X_t, X_w]), n_true


def test_gated_ransac_finds_the_pose_the_prior_allows():
    kp, X, n_true = _correspondences()
    pc = transfer.default_conf["pnp"]

    def gate(R, t):  # one pose at a time, through the report's own check
        return np.array(
            [not transfer.prior_agreement(Pose(r, v), TRUE, STD, pc)[2] for r, v in zip(R, t, strict=True)],
            bool,
        )

    pose, inl = prior_gated_pnp(kp, X, CAM.K, gate, threshold_px=6.0)
    assert pose is not None
    assert np.linalg.norm(pose.center - TRUE.center) < 0.1
    assert inl[:n_true].all() and not inl[n_true:].any()
    assert np.median(reprojection_errors(pose, CAM.K, kp[:n_true], X[:n_true])) < 1.0
    # deterministic for a seed
    pose2, inl2 = prior_gated_pnp(kp, X, CAM.K, gate, threshold_px=6.0)
    assert np.array_equal(inl, inl2) and np.allclose(pose.t, pose2.t)
    # nothing the gate allows: no pose
    assert prior_gated_pnp(kp, X, CAM.K, lambda R, t: np.zeros(len(R), bool))[0] is None
    assert prior_gated_pnp(kp[:3], X[:3], CAM.K, gate)[0] is None


def test_reducer_pnp_falls_back_to_the_gated_ransac():
    kp, X, n_true = _correspondences(seed=1)
    r = transfer.estimate_ground_pose(kp, X, CAM, TRUE, STD, transfer.default_conf)
    assert r.accepted, r.reason
    assert r.solver == "prior-gated"
    assert np.linalg.norm(np.asarray(r.center) - TRUE.center) < 0.1
    assert r.num_inliers == n_true
    # without the gated RANSAC the most-inliers pose (the wrong facade) is found and rejected by the POS
    conf = copy.deepcopy(transfer.default_conf)
    conf["pnp"]["prior_gated"] = False
    plain = transfer.estimate_ground_pose(kp, X, CAM, TRUE, STD, conf)
    assert not plain.accepted and "from the POS" in plain.reason
    assert plain.solver == "pycolmap"


def test_a_pose_that_agrees_with_the_pos_keeps_the_plain_ransac():
    kp, X, n_true = _correspondences(seed=2, n_wrong=10)
    r = transfer.estimate_ground_pose(kp, X, CAM, TRUE, STD, transfer.default_conf)
    assert r.accepted and r.solver == "pycolmap"


def test_depth_is_trusted_per_view_or_by_the_renderer():
    pc = {"depth_trust": 0.01, "min_trust_views": 3}
    names = ["a", "b", "c", "d", "low"]
    sharp = {"a": 0.002, "b": 0.004, "c": 0.003, "d": 0.05}
    # measured views by their own error; "low" (no aerial points to measure) by the renderer's median
    assert transfer.trusted_depth_views(names, sharp, pc) == [0, 1, 2, 4]
    blurry = {"a": 0.04, "b": 0.006, "c": 0.05, "d": 0.03}
    assert transfer.trusted_depth_views(names, blurry, pc) == [1]
    # too few measured views to judge the renderer
    assert transfer.trusted_depth_views(names, {"a": 0.001, "b": 0.002}, pc) == [0, 1]


def test_prior_gate_agrees_with_prior_agreement():
    """The RANSAC's fast gate (position first) passes exactly the poses prior_agreement finds no
    reason against, near and far from the prior, with the chi-square check on and off."""
    from services.reduce.localize import PriorGate, prior_agreement

    rng = np.random.default_rng(1)
    pc = dict(transfer.default_conf["pnp"])
    for chi2 in (pc["prior_chi2"], None):
        pc["prior_chi2"] = chi2
        gate = PriorGate(TRUE, STD, pc)
        verdicts = []
        for _ in range(400):
            centre = TRUE.center + rng.normal(0.0, rng.choice([1.0, 4.0, 12.0]), 3)
            w = rng.normal(0.0, np.radians(rng.choice([2.0, 8.0, 30.0])), 3)
            R = cv2.Rodrigues(w)[0] @ TRUE.R
            pose = Pose(R, -R @ centre)
            verdicts.append(gate.gate(pose))
            assert verdicts[-1] == (not prior_agreement(pose, TRUE, STD, pc)[2])
        assert 0 < sum(verdicts) < len(verdicts)  # both verdicts were tested


def test_the_batched_pieces_agree_with_one_pose_at_a_time():
    """The gated RANSAC's batches: distinct uniform samples, Rodrigues' formula, the P3P poses and their
    inlier counts as cv2 and reprojection_errors give them one at a time."""
    rng = np.random.default_rng(3)
    s = distinct_triples(rng, 7, 70000)
    assert ((s[:, 0] != s[:, 1]) & (s[:, 0] != s[:, 2]) & (s[:, 1] != s[:, 2])).all()
    assert s.min() == 0 and s.max() == 6
    counts = np.bincount(s.ravel(), minlength=7) / s.size
    assert np.abs(counts - 1 / 7).max() < 0.01
    tri = np.sort(s, 1) @ np.array([49, 7, 1])  # each of the 35 unordered triples about as often
    freq = np.unique(tri, return_counts=True)[1]
    assert len(freq) == 35 and freq.min() > 0.85 * freq.mean()

    w = rng.normal(0.0, 1.0, (50, 3))
    w[0] = 0.0
    assert np.allclose(rotations(w), [cv2.Rodrigues(v)[0] for v in w], atol=1e-12)

    kp, X, n_true = _correspondences(seed=4)
    xn = (kp - CAM.K[:2, 2]) / np.diag(CAM.K)[:2]
    samples = distinct_triples(rng, len(kp), 40)
    R, t, rows = p3p_many(xn, X, samples)
    assert len(R) >= 40 and (np.diff(rows) >= 0).all()
    for r, v, i in zip(R, t, rows, strict=True):
        cnt, rv, tv = cv2.solveP3P(X[samples[i]], xn[samples[i]], np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
        assert any(
            np.allclose(r, cv2.Rodrigues(a)[0]) and np.allclose(v, b.ravel())
            for a, b in zip(rv[:cnt], tv[:cnt], strict=True)
        )
    counts = inlier_counts(R, t, CAM.K, kp, X, 6.0)
    assert counts.tolist() == [
        int((reprojection_errors(Pose(r, v), CAM.K, kp, X) <= 6.0).sum()) for r, v in zip(R, t, strict=True)
    ]
    assert counts.max() >= n_true  # a sample of the wrong facade's points, or the true
