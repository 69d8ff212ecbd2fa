"""PnP RANSAC whose hypotheses must agree with a pose prior (the POS).

An unconstrained RANSAC returns the pose with the most inliers. Among a ground image's transferred
2D-3D correspondences the true pose may have fewer inliers than a wrong one (repeated facades, points
of one plane): the reducer then rejects the winner by the POS and the image stays unlocalized although
the right pose was there to be found. Here every minimal-sample hypothesis (P3P, up to four poses per
sample) is first checked against the prior (`gate(pose) -> bool`), and only the hypotheses that pass
are scored; the best one is refined on its inliers (local optimization: iterative PnP, inliers
recomputed, a few rounds).

    pose, inliers = prior_gated_pnp(kp, X, K, gate, threshold_px=6.0)
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from services.colmap_model import Pose


def reprojection_errors(pose: Pose, K: np.ndarray, kp: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixel distances (n,) of the projections of X (n, 3) to kp (n, 2); inf behind the camera."""
    uv, z = pose.project(K, X)
    return np.where(z > 0, np.linalg.norm(uv - kp, axis=1), np.inf)


_IDENTITY = np.eye(3)


def _p3p(xn: np.ndarray, X: np.ndarray) -> list[Pose]:
    """The poses (up to four, finite) of three normalized image points xn (3, 2) and world points X (3, 3)
    (both float64)."""
    try:
        n, rvecs, tvecs = cv2.solveP3P(X, xn, _IDENTITY, None, flags=cv2.SOLVEPNP_P3P)
    except cv2.error:
        return []
    poses = []
    for r, t in zip(rvecs[:n], tvecs[:n], strict=True):
        t = t.ravel()
        if math.isfinite(t[0]) and math.isfinite(t[1]) and math.isfinite(t[2]):
            poses.append(Pose(cv2.Rodrigues(r)[0], t))
    return poses


def refine(pose: Pose, K: np.ndarray, kp: np.ndarray, X: np.ndarray, threshold_px: float, rounds: int = 3):
    """Local optimization: iterative PnP on the inliers of `pose`, inliers recomputed, `rounds` times.
    Returns (pose, inlier mask); the pose is kept when a round would lose inliers."""
    inl = reprojection_errors(pose, K, kp, X) <= threshold_px
    for _ in range(rounds):
        if inl.sum() < 4:
            break
        rvec = cv2.Rodrigues(pose.R)[0]
        ok, rvec, tvec = cv2.solvePnP(
            X[inl].astype(np.float64),
            kp[inl].astype(np.float64),
            K.astype(np.float64),
            None,
            rvec=rvec.copy(),
            tvec=pose.t.reshape(3, 1).astype(np.float64).copy(),
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not ok:
            break
        cand = Pose(cv2.Rodrigues(rvec)[0], np.asarray(tvec, float).ravel())
        cand_inl = reprojection_errors(cand, K, kp, X) <= threshold_px
        if cand_inl.sum() < inl.sum():
            break
        done = np.array_equal(cand_inl, inl)
        pose, inl = cand, cand_inl
        if done:
            break
    return pose, inl


def prior_gated_pnp(
    kp: np.ndarray,
    X: np.ndarray,
    K: np.ndarray,
    gate: Callable[[Pose], bool],
    threshold_px: float = 6.0,
    max_trials: int = 20000,
    confidence: float = 0.999,
    seed: int = 0,
) -> tuple[Pose | None, np.ndarray]:
    """RANSAC over P3P samples of kp (n, 2) pixels and X (n, 3) world points (pinhole K), keeping only
    hypotheses with gate(pose) True. Returns (pose, inlier mask), (None, all False) when no hypothesis
    passes the gate. Deterministic for a seed."""
    kp = np.asarray(kp, float).reshape(-1, 2)
    X = np.asarray(X, float).reshape(-1, 3)
    n = len(kp)
    none = (None, np.zeros(n, bool))
    if n < 4:
        return none
    xn = (kp - K[:2, 2]) / np.diag(K)[:2]
    rng = np.random.default_rng(seed)
    best: Pose | None = None
    best_count = 0
    needed = max_trials
    trial = 0
    while trial < min(needed, max_trials):
        trial += 1
        idx = rng.choice(n, 3, replace=False)
        for pose in _p3p(xn[idx], X[idx]):
            if not gate(pose):
                continue
            count = int((reprojection_errors(pose, K, kp, X) <= threshold_px).sum())
            if count > best_count:
                best, best_count = pose, count
                w = best_count / n
                p_fail = 1.0 - w**3
                needed = 0 if p_fail <= 0 else int(math.ceil(math.log(1 - confidence) / math.log(p_fail)))
    if best is None:
        return none
    pose, inl = refine(best, K, kp, X, threshold_px)
    if not gate(pose):  # the refinement left the prior's region: keep the sampled hypothesis
        pose = best
        inl = reprojection_errors(pose, K, kp, X) <= threshold_px
    return pose, inl
