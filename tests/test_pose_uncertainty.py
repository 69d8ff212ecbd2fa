"""How well 2D-3D correspondences pin a camera's centre (services.pose_uncertainty), and the reducer's
use of it: a ground pose fixed by a patch of facade is not accepted, however many points it has."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from services import reduce as transfer
from services.colmap_model import Camera, Pose
from services.conf import merge_conf
from services.geometry import look_at
from services.pose_uncertainty import (
    DepthScale,
    depth_scale_jacobian,
    fit_pose_stds,
    pose_stds,
    position_std,
    projection_jacobian,
)

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
POSE = look_at(np.array([0.0, 0.0, 1.7]), np.array([0.0, 20.0, 4.0]))


def _points(
    rng,
    u: tuple[float, float],
    v: tuple[float, float],
    n: int = 60,
    depth: tuple[float, float] = (15.0, 30.0),
) -> tuple[np.ndarray, np.ndarray]:
    """n keypoints in the box u x v (pixels) and their points at depths in `depth` (equal: a facade
    facing the camera)."""
    kp = np.stack([rng.uniform(*u, n), rng.uniform(*v, n)], 1)
    return kp, POSE.unproject(CAM.K, kp, rng.uniform(*depth, n))


FACADE = (20.0, 20.0)
DISTANT = (60.0, 60.0)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    _, X = _points(rng, (0, 1024), (0, 768), 10)
    J = projection_jacobian(POSE, CAM.K, X)

    def project(params: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(params[3:]).as_matrix() @ POSE.R
        uv, _ = Pose.from_center(R.T, POSE.center + params[:3]).project(CAM.K, X)
        return uv.reshape(-1)

    eps = 1e-6
    num = np.stack([(project(e * eps) - project(-e * eps)) / (2 * eps) for e in np.eye(6)], 1)
    assert np.allclose(J, num, rtol=1e-4, atol=1e-3)


def test_spread_points_pin_the_centre_clustered_ones_do_not():
    rng = np.random.default_rng(1)
    _, X_spread = _points(rng, (50, 970), (50, 720))
    _, X_patch = _points(rng, (430, 600), (300, 440), depth=FACADE)  # 3% of the image: a patch of facade
    s_spread = position_std(POSE, CAM.K, X_spread, 1.0)
    s_patch = position_std(POSE, CAM.K, X_patch, 1.0)
    assert s_spread < 0.1
    assert s_patch > 10 * s_spread and s_patch > 0.5
    assert position_std(POSE, CAM.K, X_spread, 2.0) == np.float64(2.0) * s_spread  # linear in the noise
    assert position_std(POSE, CAM.K, X_spread[:2], 1.0) == float("inf")


def test_the_reducer_rejects_a_pose_its_inliers_leave_undetermined():
    """Exact correspondences in a patch of the image: the PnP pose fits them, but its centre is not
    determined to the metre; the reducer says so and does not accept it. Spread ones are accepted."""
    rng = np.random.default_rng(2)
    conf = merge_conf(transfer.default_conf, {"pnp": {"min_spread": 0.0}})  # only the new check
    kp, X = _points(rng, (430, 600), (300, 440), depth=FACADE)
    r = transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), conf)
    assert r.num_inliers >= 58 and r.position_std_m > conf["pnp"]["max_position_std_m"]
    assert not r.accepted and "ill-determined" in r.reason
    kp, X = _points(rng, (50, 970), (50, 720))
    r = transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), conf)
    assert r.accepted and r.position_std_m < 0.1
    assert np.linalg.norm(np.asarray(r.center) - POSE.center) < 0.05


def test_fit_std_takes_its_pixel_noise_from_the_residuals():
    rng = np.random.default_rng(3)
    kp, X = _points(rng, (50, 970), (50, 720))
    exact = position_std(POSE, CAM.K, X, 1.0)
    assert fit_pose_stds(POSE, CAM.K, kp, X)[0] == exact  # exact keypoints: the 1 px floor
    noisy = kp + rng.normal(0, 3.0, kp.shape)
    rms = np.sqrt(np.mean(np.sum((noisy - kp) ** 2, 1)))
    assert np.isclose(fit_pose_stds(POSE, CAM.K, noisy, X)[0], rms * exact)


def test_a_consensus_of_few_inliers_verifies_matches_but_gives_no_pose():
    """15 exact, well spread correspondences: enough for a consensus (min_inliers), too few for a pose
    (min_pose_inliers): 3D points biased by a render would go unseen by the covariance."""
    rng = np.random.default_rng(5)
    kp, X = _points(rng, (50, 970), (50, 720), n=15)
    r = transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), transfer.default_conf)
    assert r.consensus and r.num_inliers == 15 and r.position_std_m < 0.25
    assert not r.accepted and "too few for a pose" in r.reason
    kp, X = _points(rng, (50, 970), (50, 720), n=25)
    assert transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), transfer.default_conf).accepted


def test_depth_scale_jacobian_matches_finite_differences():
    """Two groups of points scaled about their views' centres, one point independent (NaN centre)."""
    rng = np.random.default_rng(6)
    _, X = _points(rng, (0, 1024), (0, 768), 9)
    centres = np.repeat([[30.0, -10.0, 8.0], [-5.0, 2.0, 20.0], [np.nan] * 3], 3, axis=0)
    E = depth_scale_jacobian(POSE, CAM.K, X, centres)
    assert E.shape == (18, 2)

    def project(e: np.ndarray) -> np.ndarray:
        groups = {tuple(c): k for k, c in enumerate(np.unique(centres[:6], axis=0))}
        Y = X.copy()
        for i in range(6):
            Y[i] = centres[i] + (1 + e[groups[tuple(centres[i])]]) * (X[i] - centres[i])
        return POSE.project(CAM.K, Y)[0].reshape(-1)

    num = np.stack([(project(d * 1e-6) - project(-d * 1e-6)) / 2e-6 for d in np.eye(2)], 1)
    assert np.allclose(E, num, rtol=1e-4, atol=1e-3)
    assert np.all(E[12:] == 0)


def test_a_pose_through_a_distant_views_surface_counts_its_depth_scale():
    """Points that take their depth from a view 40 m away, all 10% too far from it (a surface off by
    that much): the camera that sees them as the ground camera sees the true points stands 10% of 40 m
    away, fits them exactly and its plain covariance says centimetres. With the view's depth scale a
    nuisance (5%) the pose is ill-determined and not accepted; the same points from two aerial images
    (independent of the view) or through a view at the camera itself are accepted."""
    rng = np.random.default_rng(7)
    kp, X = _points(rng, (50, 970), (50, 720))
    view = POSE.center + np.array([40.0, 0.0, 0.0])
    X_off = view + 1.1 * (X - view)
    shifted = Pose.from_center(POSE.R.T, view + 1.1 * (POSE.center - view))
    assert np.allclose(shifted.project(CAM.K, X_off)[0], kp, atol=1e-6)
    conf = transfer.default_conf
    plain = transfer.estimate_ground_pose(kp, X_off, CAM, POSE, (2.5, 4.0, 2.0), conf)
    assert np.linalg.norm(np.asarray(plain.center) - POSE.center) > 3.5
    assert plain.accepted and plain.position_std_m < 0.1  # what the reducer did before
    centres = np.repeat(view[None], len(X), 0)
    r = transfer.estimate_ground_pose(kp, X_off, CAM, POSE, (2.5, 4.0, 2.0), conf, depth_centres=centres)
    assert not r.accepted and r.position_std_m > 1.0 and "ill-determined" in r.reason
    independent = np.full_like(centres, np.nan)
    r = transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), conf, depth_centres=independent)
    assert r.accepted and r.position_std_m < 0.1
    at_camera = np.repeat(POSE.center[None], len(X), 0)  # a scale about the camera's own centre: no shift
    s_at = position_std(POSE, CAM.K, X, 1.0, DepthScale(at_camera, 0.05))
    assert np.isclose(s_at, position_std(POSE, CAM.K, X, 1.0), rtol=1e-3)


def test_a_distant_facade_leaves_the_centre_uncertain_but_pins_the_attitude():
    """Points on a facade 60 m away over a third of the image: the centre is uncertain by a few decimetres
    (more than the reducer accepts), the attitude pinned within a third of a degree (what lets a ground
    pair's rotation be checked against it); on a near patch of facade a shift trades with a turn, and
    the attitude is uncertain too."""
    rng = np.random.default_rng(11)
    kp, X = _points(rng, (200, 800), (200, 560), depth=DISTANT)
    assert position_std(POSE, CAM.K, X, 1.0) > transfer.default_conf["pnp"]["max_position_std_m"]
    assert 0.0 < fit_pose_stds(POSE, CAM.K, kp, X)[1] < 0.5
    _, X_patch = _points(rng, (430, 600), (300, 440), depth=FACADE)
    assert pose_stds(POSE, CAM.K, X_patch, 1.0)[1] > 1.0
    assert pose_stds(POSE, CAM.K, X, 2.0)[1] == np.float64(2.0) * pose_stds(POSE, CAM.K, X, 1.0)[1]
    assert fit_pose_stds(POSE, CAM.K, kp[:2], X[:2]) == (float("inf"), float("inf"))


def test_the_reducer_ties_an_attitude_only_where_its_inliers_agree_with_the_pos():
    """A consensus on a distant facade: its pose is not accepted (the centre is ill-determined) but its
    attitude is tied to the aerial images; the same inliers far from the POS tie nothing."""
    rng = np.random.default_rng(11)
    conf = transfer.default_conf
    kp, X = _points(rng, (200, 800), (200, 560), depth=DISTANT)
    r = transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), conf)
    assert not r.accepted and r.consensus
    assert r.attitude_tied and r.attitude_std_deg < conf["pnp"]["max_attitude_std_deg"]
    assert r.to_dict()["attitude_tied"] and r.to_dict()["attitude_std_deg"] == r.attitude_std_deg
    far = Pose.from_center(POSE.R.T, POSE.center + np.array([40.0, 0.0, 0.0]))  # the POS 40 m off
    r = transfer.estimate_ground_pose(kp, X, CAM, far, (2.5, 4.0, 2.0), conf)
    assert r.consensus and not r.attitude_tied
    off = merge_conf(conf, {"pnp": {"max_attitude_std_deg": None}})
    assert not transfer.estimate_ground_pose(kp, X, CAM, POSE, (2.5, 4.0, 2.0), off).attitude_tied
