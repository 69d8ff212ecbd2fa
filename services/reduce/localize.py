"""Step 4 of the reducer: each ground image localized by PnP (pycolmap LO-RANSAC and refinement) on its
2D-3D correspondences, with its POS as a prior (position and attitude within `prior_sigmas` standard
deviations or the absolute floors, and jointly), and the matches that agree with the pose verified."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose
from services.pos import DEFAULT_STD_ATT, DEFAULT_STD_XY, DEFAULT_STD_Z
from services.pose_uncertainty import DepthScale, fit_pose_stds
from services.reduce.merge import Pairs
from services.reduce.observations import image_set
from services.reduce.prior_pnp import prior_gated_pnp, reprojection_errors

logger = logging.getLogger("midview.reduce")

PosStd = tuple[float, float, float]  # horizontal (m), vertical (m), attitude (deg)


@dataclass
class PoseEstimate:
    """One ground image's PnP pose and its checks. `pose`, `inliers` (correspondences within keep_px of
    it) and `errors` (their reprojection errors, px) are None when no pose was found; `accepted` when
    every check passed (else `reason` says why); `consensus` when enough correspondences agree on one
    camera to verify matches even if the pose itself is not accepted; `attitude_tied` when its attitude
    alone can be trusted though its position may not (a consensus through two views at least, agreeing
    with the POS, its attitude pinned within pnp.max_attitude_std_deg)."""

    num_correspondences: int
    accepted: bool = False
    reason: str = ""
    solver: str | None = None
    pose: Pose | None = None
    inliers: np.ndarray | None = None
    errors: np.ndarray | None = None
    position_std_m: float | None = None
    inlier_spread: float | None = None
    consensus: bool = False
    to_pos: dict[str, float] | None = None
    limits: dict[str, float] | None = None
    trusted_depth_inliers: int | None = None
    inlier_views: dict[str, int] | None = None  # the inliers by the rendered view they came through
    attitude_std_deg: float | None = None  # the attitude's std about its worst axis, from the inliers
    attitude_tied: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def num_inliers(self) -> int:
        return 0 if self.inliers is None else int(self.inliers.sum())

    @property
    def inlier_ratio(self) -> float:
        return 0.0 if self.inliers is None or len(self.inliers) == 0 else float(self.inliers.mean())

    @property
    def center(self) -> list[float] | None:
        return None if self.pose is None else self.pose.center.tolist()

    def verifies(self, pc: dict) -> bool:
        """Whether matches may be checked against this pose: accepted, or a consensus (when allowed)."""
        return self.pose is not None and (self.accepted or bool(pc["verify_on_consensus"] and self.consensus))

    def to_dict(self) -> dict[str, Any]:
        """The JSON record of ground_poses.json and the reports."""
        d: dict[str, Any] = {"num_correspondences": self.num_correspondences, "accepted": self.accepted}
        d["reason"] = self.reason
        if self.pose is not None:
            d.update(
                solver=self.solver,
                R=self.pose.R.tolist(),
                t=self.pose.t.tolist(),
                center=self.center,
                num_inliers=self.num_inliers,
                inlier_ratio=self.inlier_ratio,
                consensus=self.consensus,
                attitude_tied=self.attitude_tied,
            )
        optional = ("position_std_m", "inlier_spread", "to_pos", "limits")
        for k in (*optional, "attitude_std_deg", "trusted_depth_inliers", "inlier_views"):
            if getattr(self, k) is not None:
                d[k] = getattr(self, k)
        return {**d, **self.extra}


def _chi2_sigmas(std: tuple[float, float, float], pc: dict) -> tuple[float, float, float]:
    """The standard deviations of prior_chi2: horizontal (m), vertical (m), rotation (deg), each at least
    its floor (min_position_m etc.) / prior_sigmas."""
    k = pc["prior_sigmas"]
    sxy = max(std[0], pc["min_position_m"] / (k * math.sqrt(2.0)))
    sz = max(std[1], pc["min_height_m"] / k)
    satt = max(std[2], pc["min_rotation_deg"] / (k * math.sqrt(3.0)))
    return sxy, sz, satt


def prior_chi2(dxy: float, dz: float, drot: float, std: tuple[float, float, float], pc: dict) -> float:
    """Squared normalized difference of a pose to its POS: horizontal (m), vertical (m) and rotation
    (deg) over their standard deviations (_chi2_sigmas)."""
    sxy, sz, satt = _chi2_sigmas(std, pc)
    return float((dxy / sxy) ** 2 + (dz / sz) ** 2 + (drot / satt) ** 2)


class PriorGate:
    """A POS prior's limits, set once: `differences(pose)` and `reasons(...)` for one pose's report,
    `gate(pose)` (no reason: it agrees) for the many hypotheses of a RANSAC. Position and attitude each
    within prior_sigmas standard deviations (or the floors), and jointly (chi-square)."""

    def __init__(self, prior: Pose, prior_std: tuple[float, float, float] | None, pc: dict):
        self.center = prior.center
        self.R = prior.R
        self.std = prior_std or (DEFAULT_STD_XY, DEFAULT_STD_Z, DEFAULT_STD_ATT)
        sxy, sz, satt = self.std
        k = pc["prior_sigmas"]
        self.pc = pc
        self.limits = {
            "horizontal_m": max(k * sxy * math.sqrt(2.0), pc["min_position_m"]),
            "vertical_m": max(k * sz, pc["min_height_m"]),
            "rotation_deg": max(k * satt * math.sqrt(3.0), pc["min_rotation_deg"]),
        }
        self._chi2_max = pc.get("prior_chi2") or math.inf

    def _position(self, pose: Pose) -> tuple[float, float]:
        d = pose.center - self.center
        return math.sqrt(d[0] * d[0] + d[1] * d[1]), abs(float(d[2]))

    def _rotation(self, pose: Pose) -> float:
        cos = (float(np.vdot(pose.R, self.R)) - 1.0) / 2.0  # trace(R Rp^T) = sum(R * Rp)
        return math.degrees(math.acos(min(1.0, max(-1.0, cos))))

    def differences(self, pose: Pose) -> tuple[float, float, float, float]:
        """(horizontal m, vertical m, rotation deg, chi-square) of pose to the prior."""
        dxy, dz = self._position(pose)
        drot = self._rotation(pose)
        return dxy, dz, drot, prior_chi2(dxy, dz, drot, self.std, self.pc)

    def gate(self, pose: Pose) -> bool:
        """Whether the pose agrees with the prior (no reason of `reasons`)."""
        return bool(self.agree(pose.R[None], pose.t[None])[0])

    def agree(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """gate() of many poses at once: R (P, 3, 3) and t (P, 3) cam_from_world -> (P,) bool."""
        lim_xy, lim_z, lim_rot = self.limits.values()
        d = -np.einsum("pji,pj->pi", R, t) - self.center  # camera centres less the prior's
        dxy, dz = np.hypot(d[:, 0], d[:, 1]), np.abs(d[:, 2])
        cos = (np.einsum("pij,ij->p", R, self.R) - 1.0) / 2.0
        drot = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        sxy, sz, satt = _chi2_sigmas(self.std, self.pc)
        chi2 = (dxy / sxy) ** 2 + (dz / sz) ** 2 + (drot / satt) ** 2
        return (dxy <= lim_xy) & (dz <= lim_z) & (drot <= lim_rot) & (chi2 <= self._chi2_max)

    def reasons(self, dxy: float, dz: float, drot: float, chi2: float) -> list[str]:
        """Why differences disagree with the prior (none: they agree)."""
        lim_xy, lim_z, lim_rot = self.limits.values()
        out = []
        if dxy > lim_xy:
            out.append(f"{dxy:.1f} m from the POS horizontally (> {lim_xy:.1f})")
        if dz > lim_z:
            out.append(f"{dz:.1f} m from the POS vertically (> {lim_z:.1f})")
        if drot > lim_rot:
            out.append(f"{drot:.1f} deg from the POS attitude (> {lim_rot:.1f})")
        if chi2 > self._chi2_max:
            out.append(f"position and attitude jointly {chi2:.1f} (chi-square > {self._chi2_max:.1f})")
        return out


def prior_agreement(
    pose: Pose, prior: Pose, prior_std: tuple[float, float, float] | None, pc: dict
) -> tuple[dict, dict, list[str]]:
    """How far `pose` is from its POS `prior`: (differences, limits, reasons it disagrees), see PriorGate."""
    g = PriorGate(prior, prior_std, pc)
    dxy, dz, drot, chi2 = g.differences(pose)
    to_pos = {"horizontal_m": dxy, "vertical_m": dz, "rotation_deg": drot, "chi2": chi2}
    return to_pos, dict(g.limits), g.reasons(dxy, dz, drot, chi2)


def _solve_pnp(
    kp: np.ndarray, X: np.ndarray, camera: Camera, prior: Pose | None, prior_std: PosStd | None, pc: dict
) -> tuple[Pose | None, str]:
    """(pose, solver): pycolmap's LO-RANSAC pose; when it disagrees with the POS (and prior_gated), the
    best pose of a second RANSAC that keeps only hypotheses agreeing with it (services.reduce.prior_pnp)."""
    import pycolmap

    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = float(pc["ransac_px"])
    opts.ransac.random_seed = int(pc["seed"])
    opts.ransac.min_inlier_ratio = 0.05
    opts.ransac.max_num_trials = 20000
    try:
        out = pycolmap.estimate_and_refine_absolute_pose(
            np.ascontiguousarray(kp, np.float64),
            np.ascontiguousarray(X, np.float64),
            camera.to_pycolmap(1),
            opts,
        )
    except Exception as e:  # pycolmap raises on degenerate input
        out = None
        logger.debug("PnP failed: %s", e)
    pose = None
    if out is not None:
        m = np.asarray(out["cam_from_world"].matrix())
        pose = Pose(m[:, :3].copy(), m[:, 3].copy())
    gate = PriorGate(prior, prior_std, pc) if prior is not None else None
    disagrees = pose is None or (gate is not None and not gate.gate(pose))
    if gate is not None and pc["prior_gated"] and disagrees:
        gated, _ = prior_gated_pnp(kp, X, camera.K, gate.agree, pc["ransac_px"], seed=int(pc["seed"]))
        if gated is not None:
            return gated, "prior-gated"
    return pose, "pycolmap"


def _inlier_checks(
    est: PoseEstimate,
    kp: np.ndarray,
    X: np.ndarray,
    camera: Camera,
    pc: dict,
    views: np.ndarray | None,
    depth_centres: np.ndarray | None = None,
) -> list[str]:
    """Why the inliers of est do not make an accepted pose (none: they do): how well they pin the camera
    centre (with `depth_centres`, each view's depth scale a nuisance: DepthScale), how much of the image
    they cover, how many there are and their ratio, and (with `views`, the rendered view each
    correspondence came through) whether views other than the largest confirm them.
    Sets est's position_std_m, attitude_std_deg, inlier_spread, inlier_views, consensus and
    attitude_tied (before the POS is checked)."""
    inl = est.inliers
    reasons = []
    confirmed = True
    if views is not None:
        names, counts = np.unique(views[inl], return_counts=True)
        est.inlier_views = {str(n): int(c) for n, c in zip(names, counts, strict=True)}
        others = int(inl.sum()) - (int(counts.max()) if len(counts) else 0)
        confirmed = others >= pc["min_other_view_inliers"]
        if not confirmed:
            reasons.append(
                f"{others} inliers through views other than the largest (< {pc['min_other_view_inliers']}):"
                " one view's matches alone"
            )
    if inl.sum() >= 3:  # pixel noise: their RMS residual, at least 1 px
        scale = None
        if depth_centres is not None and pc.get("depth_scale_std"):
            scale = DepthScale(depth_centres[inl], float(pc["depth_scale_std"]))
        std, est.attitude_std_deg = fit_pose_stds(est.pose, camera.K, kp[inl], X[inl], scale=scale)
        est.position_std_m = std
        if pc.get("max_position_std_m") and std > pc["max_position_std_m"]:
            reasons.append(
                f"position ill-determined by its inliers: std {std:.2f} m (> {pc['max_position_std_m']})"
            )
    if inl.any():
        span = kp[inl].max(0) - kp[inl].min(0)
        est.inlier_spread = float(span[0] * span[1] / (camera.width * camera.height))
        if est.inlier_spread < pc.get("min_spread", 0.0):
            reasons.append(
                f"inliers cover {100 * est.inlier_spread:.1f}% of the image (< {100 * pc['min_spread']:.0f}%)"
            )
    n = int(inl.sum())
    if n < pc["min_inliers"]:
        reasons.append(f"{n} inliers (< {pc['min_inliers']})")
    elif n < pc.get("min_pose_inliers", 0):
        reasons.append(f"{n} inliers verify matches but are too few for a pose (< {pc['min_pose_inliers']})")
    if inl.mean() < pc["min_inlier_ratio"]:
        reasons.append(f"inlier ratio {inl.mean():.2f} (< {pc['min_inlier_ratio']})")
    # enough correspondences agree on one camera: they verify the matches even where the pose itself is
    # ill-determined (clustered or planar points) and fails the spread check above or the POS checks
    est.consensus = bool(n >= pc["min_inliers"] and inl.mean() >= pc["min_inlier_ratio"])
    # its attitude can be trusted where its position cannot (distant points pin a turn, not a shift): the
    # combined SfM checks ground pairs' relative rotations against it (services.sfm.combined)
    max_att, att = pc.get("max_attitude_std_deg"), est.attitude_std_deg
    est.attitude_tied = bool(est.consensus and confirmed and max_att and att is not None and att <= max_att)
    return reasons


def estimate_ground_pose(
    kp: np.ndarray,
    X: np.ndarray,
    camera: Camera,
    prior: Pose | None,
    prior_std: PosStd | None,
    conf: dict,
    views: np.ndarray | None = None,
    depth_centres: np.ndarray | None = None,
) -> PoseEstimate:
    """PnP LO-RANSAC of one ground image (keypoints kp (n, 2), points X (n, 3)) with its POS as a prior;
    `views` (n,): the name of the rendered view each correspondence came through (None: direct matches);
    `depth_centres` (n, 3): the centre of the view whose surface gave each point its depth (NaN: none)."""
    pc = conf["pnp"]
    est = PoseEstimate(num_correspondences=int(len(kp)))
    if len(kp) < max(pc["min_inliers"], 4):
        est.reason = f"{len(kp)} correspondences (< {pc['min_inliers']})"
        return est
    pose, solver = _solve_pnp(kp, X, camera, prior, prior_std, pc)
    if pose is None:
        est.reason = "PnP RANSAC found no pose"
        return est
    est.pose, est.solver = pose, solver
    est.errors = reprojection_errors(pose, camera.K, kp, X)
    est.inliers = est.errors <= pc["keep_px"]
    reasons = _inlier_checks(est, kp, X, camera, pc, views, depth_centres)
    if prior is not None:
        est.to_pos, est.limits, prior_reasons = prior_agreement(pose, prior, prior_std, pc)
        reasons += prior_reasons
        est.attitude_tied = est.attitude_tied and not prior_reasons
    est.accepted = not reasons
    est.reason = "; ".join(reasons) if reasons else "ok"
    return est


def trusted_depth_views(view_names: list[str], depth_error: dict[str, float], pc: dict) -> list[int]:
    """Indices of the views whose rendered depth lifts ground matches to 3D: median relative difference
    to their triangulated aerial points <= depth_trust. A view without aerial points to measure (a low
    view that matches only the ground image) is trusted when the renderer is: the median over the
    measured views (at least min_trust_views of them) is within depth_trust."""
    tol = pc["depth_trust"]
    measured = list(depth_error.values())
    renderer_ok = len(measured) >= pc["min_trust_views"] and float(np.median(measured)) <= tol
    return [
        i for i, n in enumerate(view_names) if (depth_error[n] <= tol if n in depth_error else renderer_ok)
    ]


def ground_priors(
    pos: str | Path | list, georef: str | Path
) -> tuple[dict[str, Pose], dict[str, tuple[float, float, float]]]:
    """Ground POS poses in the aerial model frame and their standard deviations."""
    from services.geometry import pos_in_frame
    from services.pos import read_pos
    from services.sfm import read_georef_frame

    records = read_pos(pos) if isinstance(pos, str | Path) else list(pos)
    frame = read_georef_frame(georef)
    poses, std = {}, {}
    for n, (pose, _, r) in pos_in_frame(records, frame).items():
        if image_set(n) != "ground" or pose is None:
            continue
        poses[n] = pose
        std[n] = r.std_or_default()
    return poses, std


def _correspondences(
    g: str, merged: Pairs, og: dict[str, np.ndarray], depth_points: bool | str, trusted_views: list[int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ground keypoint indices, 3D points, whether from a trusted view's rendered depth, the view each
    came through, whether its depth is that view's surface's) of ground image g: its merged links' points
    and, with depth_points, its render matches lifted by the rendered depth (only the trusted views' with
    "trusted"); one point per ground keypoint, the best-scored. A link's point takes its depth from its
    view's surface when a single aerial image observes it (the view's ray and that image's ray cross
    where the view took the pixel's colour); a lifted point always does."""
    keys = [k for k in merged if k[1] == g]
    ig = np.concatenate([merged[k]["ig"] for k in keys]) if keys else np.zeros(0, np.int64)
    X = np.concatenate([merged[k]["X"] for k in keys]) if keys else np.zeros((0, 3))
    sc = np.concatenate([merged[k]["score"] for k in keys]) if keys else np.zeros(0, np.float32)
    view = np.concatenate([merged[k]["view"] for k in keys]) if keys else np.zeros(0, np.int64)
    n_aerial = np.concatenate([merged[k]["n_aerial"] for k in keys]) if keys else np.zeros(0, np.int64)
    on_surface = n_aerial < 2
    from_depth = np.zeros(len(ig), bool)
    if depth_points:
        has_x = np.isfinite(og["X"]).all(1)
        trusted = np.isin(og["view"], trusted_views)
        if depth_points == "trusted":
            has_x &= trusted
        ig = np.concatenate([ig, og["i"][has_x]])
        X = np.concatenate([X, og["X"][has_x]])
        sc = np.concatenate([sc, og["score"][has_x]])
        view = np.concatenate([view, og["view"][has_x]])
        from_depth = np.concatenate([from_depth, trusted[has_x]])
        on_surface = np.concatenate([on_surface, np.ones(int(has_x.sum()), bool)])
    order = np.lexsort((-sc.astype(np.float64), ig))
    first = np.ones(len(order), bool)
    first[1:] = ig[order][1:] != ig[order][:-1]
    sel = order[first]
    return ig[sel], X[sel], from_depth[sel], view[sel], on_surface[sel]


def localize_grounds(
    merged: Pairs,
    obs: dict[str, dict[str, np.ndarray]],
    keypoints: dict[str, np.ndarray],
    ground_camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
    depth_error: dict[str, float],
    view_names: list[str],
    conf: dict,
    view_centres: np.ndarray | None = None,
) -> tuple[dict[str, PoseEstimate], dict[tuple[str, str], np.ndarray]]:
    """(pose per ground image, verified mask per pair): PnP of each ground image on its correspondences
    (pnp.depth_points: also its render matches lifted by the rendered depth, of the trusted views only
    when "trusted"), then its pairs' matches within keep_px of the pose, or all of them (unverified
    "fundamental") or none where the pose cannot verify them. `view_centres` (views, 3): the views'
    centres, for the depth scale of the points their surfaces gave (pnp.depth_scale_std)."""
    pc = conf["pnp"]
    trusted = trusted_depth_views(view_names, depth_error, pc) if pc["depth_points"] else []
    poses: dict[str, PoseEstimate] = {}
    verified: dict[tuple[str, str], np.ndarray] = {}
    for g in sorted(n for n in obs if image_set(n) == "ground"):
        ig, X, from_depth, view, on_surface = _correspondences(g, merged, obs[g], pc["depth_points"], trusted)
        kp = keypoints[g][ig].astype(np.float64)
        names = np.array(view_names, dtype=object)[view] if len(view) else np.zeros(0, object)
        centres = None
        if view_centres is not None:
            centres = np.where(on_surface[:, None], view_centres[view].reshape(-1, 3), np.nan)
        est = estimate_ground_pose(
            kp, X, ground_camera, priors.get(g), prior_std.get(g), conf, names, centres
        )
        if est.inliers is not None:  # inliers whose 3D point is the rendered depth of a view trusted for it
            est.trusted_depth_inliers = int((from_depth & est.inliers).sum())
        poses[g] = est
        for key in (k for k in merged if k[1] == g):
            m = merged[key]
            if est.verifies(pc):
                uv, z = est.pose.project(ground_camera.K, m["X"])
                err = np.where(z > 0, np.linalg.norm(uv - keypoints[g][m["ig"]], axis=1), np.inf)
                verified[key] = err <= pc["keep_px"]
            else:
                verified[key] = np.full(len(m["ia"]), conf["unverified"] == "fundamental")
    return poses, verified
