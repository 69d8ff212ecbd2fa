"""PnP RANSAC whose hypotheses must agree with a pose prior (the POS).

An unconstrained RANSAC returns the pose with the most inliers. Among a ground image's transferred
2D-3D correspondences the true pose may have fewer inliers than a wrong one (repeated facades, points
of one plane): the reducer then rejects the winner by the POS and the image stays unlocalized although
the right pose was there to be found. Here every minimal-sample hypothesis (P3P, up to four poses per
sample) is first checked against the prior (`agree(R, t) -> bool` per pose, many at once), and only the
hypotheses that pass are scored; the best one is refined on its inliers (local optimization: iterative
PnP, inliers recomputed, a few rounds).

    pose, inliers = prior_gated_pnp(kp, X, K, PriorGate(prior, std, pc).agree, threshold_px=6.0)
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


def distinct_triples(rng: np.random.Generator, n: int, m: int) -> np.ndarray:
    """m uniform samples (m, 3) int64 of three distinct indices in [0, n) (n >= 3): the second and third
    drawn from the n - 1 and n - 2 indices left and shifted past those taken."""
    a = rng.integers(0, n, m)
    b = rng.integers(0, n - 1, m)
    c = rng.integers(0, n - 2, m)
    b += b >= a
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    c += c >= lo
    c += c >= hi
    return np.stack([a, b, c], 1)


def rotations(rvecs: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for many rotation vectors: (P, 3) -> (P, 3, 3)."""
    theta = np.linalg.norm(rvecs, axis=1)
    k = rvecs / np.where(theta > 1e-12, theta, 1.0)[:, None]
    K = np.zeros((len(rvecs), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - K.transpose(0, 2, 1)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def p3p_many(xn: np.ndarray, X: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The finite P3P poses of each sample (m, 3) of normalized image points xn (n, 2) and world points X
    (n, 3): R (P, 3, 3), t (P, 3) cam_from_world and the sample (row) each pose came from (P,)."""
    rvecs, tvecs, rows = [], [], []
    for i, idx in enumerate(samples):
        try:
            count, rv, tv = cv2.solveP3P(X[idx], xn[idx], _IDENTITY, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        for r, t in zip(rv[:count], tv[:count], strict=True):
            rvecs.append(r.ravel())
            tvecs.append(t.ravel())
            rows.append(i)
    if not rows:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    r, t, i = np.array(rvecs, float), np.array(tvecs, float), np.array(rows, np.int64)
    finite = np.isfinite(t).all(1) & np.isfinite(r).all(1)
    return rotations(r[finite]), t[finite], i[finite]


def inlier_counts(
    R: np.ndarray, t: np.ndarray, K: np.ndarray, kp: np.ndarray, X: np.ndarray, threshold_px: float
) -> np.ndarray:
    """How many of kp (n, 2) / X (n, 3) each pose (R (P, 3, 3), t (P, 3)) reprojects within threshold_px
    (points behind the camera are outliers), as reprojection_errors counts them: (P,) int."""
    out = np.zeros(len(R), np.int64)
    f, c = np.diag(K)[:2], K[:2, 2]
    step = max(1, 2_000_000 // max(1, len(X)))  # at most ~2M points projected at once
    for s in range(0, len(R), step):
        Xc = np.einsum("pij,nj->pni", R[s : s + step], X) + t[s : s + step, None, :]
        z = Xc[..., 2]
        uv = Xc[..., :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[..., None] * f + c
        d2 = ((uv - kp) ** 2).sum(-1)
        out[s : s + step] = ((z > 0) & (d2 <= threshold_px**2)).sum(1)
    return out


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
    agree: Callable[[np.ndarray, np.ndarray], np.ndarray],
    threshold_px: float = 6.0,
    max_trials: int = 20000,
    confidence: float = 0.999,
    seed: int = 0,
    batch: int = 256,
) -> tuple[Pose | None, np.ndarray]:
    """RANSAC over P3P samples of kp (n, 2) pixels and X (n, 3) world points (pinhole K), keeping only
    hypotheses the prior allows: agree(R (P, 3, 3), t (P, 3)) -> (P,) bool. Returns (pose, inlier mask),
    (None, all False) when no hypothesis passes. Deterministic for a seed.

    The samples are drawn, solved, gated and scored `batch` at a time, then taken in order as one at a
    time would: the best pose so far, and the trials it leaves needed for `confidence`."""
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
    trial = 0  # trials drawn so far
    while trial < min(needed, max_trials):
        samples = distinct_triples(rng, n, min(batch, max_trials - trial))
        R, t, rows = p3p_many(xn, X, samples)
        ok = agree(R, t) if len(R) else np.zeros(0, bool)
        counts = inlier_counts(R[ok], t[ok], K, kp, X, threshold_px)
        current = -1  # the trial whose poses are being taken: all of them, as one at a time would
        for j, count in zip(np.flatnonzero(ok), counts, strict=True):
            if trial + rows[j] != current and trial + rows[j] >= min(needed, max_trials):
                break  # a trial the confidence no longer needs
            current = trial + rows[j]
            if count > best_count:
                best, best_count = Pose(R[j].copy(), t[j].copy()), int(count)
                p_fail = 1.0 - (best_count / n) ** 3
                needed = 0 if p_fail <= 0 else int(math.ceil(math.log(1 - confidence) / math.log(p_fail)))
        trial += len(samples)
    if best is None:
        return none
    pose, inl = refine(best, K, kp, X, threshold_px)
    if not agree(pose.R[None], pose.t[None])[0]:  # the refinement left the prior's region: keep the sample
        pose = best
        inl = reprojection_errors(pose, K, kp, X) <= threshold_px
    return pose, inl
