"""Georeferencing: a similarity from the reconstruction to local ENU, from the POS positions and attitudes.

Two steps. First a robust initial similarity from the camera centres (pycolmap's LO-RANSAC,
`estimate_sim3d_robust`, inlier threshold scaled to the POS std), or, when the centres are nearly
collinear and the POS has attitudes, the rotation from those (robust chordal mean of
R_pos @ R_rec^T) with scale and translation from the centres.

Then a joint weighted least-squares refinement (`refine_joint`) over every image, each term weighted
by its stated std or, where the POS states none, by the noise estimated from the residuals (per axis:
horizontal, vertical, attitude): the centres; the POS attitudes where given; and, where no attitude is
given, an orientation prior as OpenSfM's `align_orientation_prior` (camera x axes horizontal, "no roll",
and for nadir flights the y axes too, "vertical"), its weight from the spread of the cameras' own axes.
Centres flown at one height fix the tilt only to the vertical noise over the flight's extent; the
attitudes fix it to their noise over the square root of their number. The refinement's covariance
gives the rotation (tilt and heading), scale and position uncertainty reported in georef.json and the
SfM report.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from services.geometry import rotation_angle_deg
from services.pos import LocalFrame, PosRecord

logger = logging.getLogger("midview.sfm.georef")

default_conf = {
    "max_error_sigmas": 3.0,  # RANSAC inlier threshold: this many POS standard deviations ...
    "min_max_error": 0.5,  # ... but at least this many metres
    "collinear_ratio": 0.05,  # second / first singular value of the centred positions below this
    "max_rotation_uncertainty_deg": 3.0,  # sigma / s2 above this: the centres do not fix the rotation
    "attitude_inlier_deg": 10.0,  # attitudes within this of the consensus rotation are used
    "coplanar_ratio": 0.05,  # third / second singular value below this: coplanar (reported only)
    "min_images": 3,
    "seed": 0,
    # status "suspect" when fewer than this share of the cameras are inliers, or the mean residual is
    # above the inlier threshold, or the median attitude residual above attitude_inlier_deg;
    # "failed" when fewer than min_images cameras are inliers
    "min_inlier_ratio": 0.5,
    # the joint refinement (centres, attitudes, orientation prior); False: the initial similarity only
    "joint": True,
    # "auto": none where most images have a POS attitude; else "level" for a flight at one height (its
    # centres coplanar, coplanar_ratio: a wind-tilted unstabilised camera biases the axes, an altitude
    # hold does not), "vertical" for nadir flights (optical axes within nadir_spread_deg of their mean,
    # median) and "no_roll" otherwise; or name one, or "none"
    "orientation_prior": "auto",
    "nadir_spread_deg": 15.0,
    "level_ratio": 0.25,  # "level": the centres' std off their plane below this share of its width
    "min_prior_std_deg": 0.5,  # floor of the prior's per-image std (estimated from the axes' spread)
    "min_level_std_m": 0.05,  # floor of the "level" prior's std of the centres off their plane
    "min_noise_images": 6,  # fewer images: the POS noise is not estimated from the residuals
    "min_pos_std_m": 0.02,  # floors of estimated noise
    "min_att_std_deg": 0.1,
    "noise_iterations": 3,  # refit, re-estimate the unstated noise, refit ...
    "robust_sigmas": 2.5,  # Huber loss beyond this many stds
    # the POS heights' tilt against the attitudes' or prior's, in that tilt's stds, above which the
    # heights are taken as tilted (systematic) and the tilt comes from the attitudes or prior alone
    "height_trend_sigmas": 4.0,
    "max_tilt_std_deg": 1.0,  # status "suspect" when the fit's 1-sigma tilt is above this
}


class GeorefError(RuntimeError):
    """Too few registered images with POS, or a degenerate configuration."""


@dataclass
class Georef:
    """tgt_from_src similarity (ENU from reconstruction) and its quality."""

    scale: float
    R: np.ndarray
    t: np.ndarray
    method: str
    condition: dict
    inliers: dict[str, bool] = field(default_factory=dict)
    residuals: dict[str, np.ndarray] = field(default_factory=dict)  # name -> ENU residual vector (m)
    attitude_deg: dict[str, float] = field(default_factory=dict)
    noise: dict = field(default_factory=dict)  # POS noise used for the weights, and where it came from
    uncertainty: dict = field(default_factory=dict)  # 1-sigma rotation, scale and position of the fit
    levels: dict = field(default_factory=dict)  # the georeferenced flight's plane and axes (tilt_figures)

    @property
    def sim3d(self) -> pycolmap.Sim3d:
        return pycolmap.Sim3d(self.scale, pycolmap.Rotation3d(self.R), self.t)

    def apply(self, X: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(X) @ self.R.T + self.t


def condition(points: np.ndarray, sigma: float = 0.0, conf: dict | None = None) -> dict:
    """Singular values of centred points, whether they are (nearly) collinear or coplanar, and the
    uncertainty of a rotation fitted to them with position noise `sigma` (degrees)."""
    conf = {**default_conf, **(conf or {})}
    P = np.asarray(points, float)
    s = np.linalg.svd(P - P.mean(0), compute_uv=False) if len(P) > 1 else np.zeros(3)
    s = np.pad(s, (0, 3 - len(s)))
    s1 = max(float(s[0]), 1e-12)
    collinear = bool(s[1] / s1 < conf["collinear_ratio"])
    coplanar = bool(not collinear and s[2] / max(float(s[1]), 1e-12) < conf["coplanar_ratio"])
    uncertainty = float(np.degrees(min(sigma / max(float(s[1]), 1e-12), np.pi)))
    return {
        "singular_values": [float(v) for v in s],
        "collinear": collinear,
        "coplanar": coplanar,
        "rotation_uncertainty_deg": uncertainty,
        "ill_conditioned": collinear or uncertainty > conf["max_rotation_uncertainty_deg"],
    }


def mean_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    """Chordal L2 mean of rotation matrices (projection of their sum onto SO(3))."""
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def robust_mean_rotation(Rs: list[np.ndarray], inlier_deg: float) -> tuple[np.ndarray, int]:
    """Chordal mean of the rotations within `inlier_deg` of the one with most such neighbours."""
    counts = [sum(rotation_angle_deg(a.T @ b) <= inlier_deg for b in Rs) for a in Rs]
    best = Rs[int(np.argmax(counts))]
    inl = [b for b in Rs if rotation_angle_deg(best.T @ b) <= inlier_deg]
    return mean_rotation(inl), len(inl)


def _similarity_from_attitudes(src: np.ndarray, tgt: np.ndarray, R: np.ndarray) -> tuple[float, np.ndarray]:
    """Scale and translation given the rotation (least squares on the centres)."""
    a, b = src - src.mean(0), tgt - tgt.mean(0)
    ra = a @ R.T
    s = float(np.sum(ra * b) / max(np.sum(ra * ra), 1e-12))
    return s, tgt.mean(0) - s * R @ src.mean(0)


def _robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation from the median (a Gaussian's std, robust to outliers)."""
    x = np.asarray(x, float).ravel()
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else 0.0


def tilt_figures(centres: np.ndarray, R_world_from_cam: list[np.ndarray] | None = None) -> dict:
    """How level a georeferenced flight stands: the angle (deg) between the vertical and the normal of
    the plane fitted to the camera centres (meaningful for a flight at one height: its centres nearly
    coplanar), the centres' std off that plane (m), and the median angle of the optical axes from
    straight down (a nadir flight's)."""
    C = np.asarray(centres, float)
    out: dict = {"flight_plane_tilt_deg": None, "off_plane_std_m": None, "optical_axis_from_nadir_deg": None}
    if len(C) >= 3:
        _, sv, Vt = np.linalg.svd(C - C.mean(0))
        normal = Vt[2]
        out["flight_plane_tilt_deg"] = float(np.degrees(np.arccos(min(abs(normal[2]), 1.0))))
        out["off_plane_std_m"] = float(sv[2] / np.sqrt(len(C)))
    if R_world_from_cam:
        down = np.array([R[2, 2] for R in R_world_from_cam])  # optical axis . up
        out["optical_axis_from_nadir_deg"] = float(np.median(np.degrees(np.arccos(np.clip(-down, -1, 1)))))
    return out


def choose_prior(R_rec: list[np.ndarray] | None, n_attitudes: int, conf: dict, src=None) -> str:
    """The orientation prior of the joint fit: "none"; "level" (a flight at one height: its centres'
    plane is horizontal); "vertical" (nadir: the camera x and y axes horizontal); "no_roll" (x axes)."""
    kind = conf["orientation_prior"]
    if kind != "auto":
        return kind
    if not R_rec or n_attitudes >= 0.5 * len(R_rec):
        return "none"
    if src is not None and len(src) >= conf["min_noise_images"]:
        sv = np.linalg.svd(np.asarray(src, float) - np.mean(src, 0), compute_uv=False)
        if sv[2] < conf["level_ratio"] * sv[1]:
            return "level"
    axes = np.array([R[:, 2] for R in R_rec])  # optical axes in the reconstruction
    mean = axes.sum(0) / max(np.linalg.norm(axes.sum(0)), 1e-12)
    spread = np.degrees(np.arccos(np.clip(axes @ mean, -1.0, 1.0)))
    return "vertical" if float(np.median(spread)) < conf["nadir_spread_deg"] else "no_roll"


def stations(src: np.ndarray, rel_tol: float = 1e-3) -> np.ndarray:
    """(N,) index of the station of each camera: cameras of one rig exposure (a multi-head oblique
    camera) share a centre, within rel_tol of the flight's extent, and count once for the "level"
    prior (five heads at one station are one altitude sample, not five)."""
    P = np.asarray(src, float)
    tol = rel_tol * max(float(np.linalg.norm(P.std(0))), 1e-12)
    ids = -np.ones(len(P), int)
    for i in range(len(P)):
        if ids[i] < 0:
            ids[(ids < 0) & (np.linalg.norm(P - P[i], axis=1) <= tol)] = ids.max() + 1
    return ids


def level_std(src: np.ndarray, floor: float) -> float:
    """The stations' std off their best plane (reconstruction units), at least `floor`."""
    ids = stations(src)
    P = np.array([np.asarray(src, float)[ids == k].mean(0) for k in range(ids.max() + 1)])
    sv = np.linalg.svd(P - P.mean(0), compute_uv=False) if len(P) >= 3 else np.zeros(3)
    return max(float(sv[2]) / np.sqrt(max(len(P), 1)), floor)


def _prior_axes(kind: str) -> list[int]:
    """Camera axes (columns of R_world_from_cam) that the prior holds horizontal."""
    return {"none": [], "level": [], "no_roll": [0], "vertical": [0, 1]}[kind]


def prior_spread_deg(R_rec: list[np.ndarray], kind: str, floor_deg: float) -> np.ndarray:
    """The per-image std (degrees) of each prior axis, from the cameras' own scatter, whatever the
    frame: for "vertical" the x and y axes against the mean optical axis; for "no_roll" the x axes
    against the normal of their best plane. (Measured against the vertical of a wrong frame, the
    scatter would absorb the frame's tilt and weaken the prior that should correct it.)"""
    axes = _prior_axes(kind)
    if not axes:
        return np.zeros(0)
    if kind == "vertical":
        up = np.sum([R[:, 2] for R in R_rec], axis=0)
    else:
        up = np.linalg.svd(np.array([R[:, 0] for R in R_rec]), full_matrices=False)[2][-1]
    up = up / max(np.linalg.norm(up), 1e-12)
    # about zero, not about their median: a constant tilt in the camera frame (a multicopter pitched
    # into its flight direction) is each image's deviation too, and averages out over the flight lines
    spread = [1.4826 * float(np.median(np.abs([up @ R[:, k] for R in R_rec]))) for k in axes]
    return np.maximum(np.degrees(np.arcsin(np.clip(spread, 0.0, 1.0))), floor_deg)


@dataclass
class JointTerms:
    """What the joint fit weighs: centres with per-axis stds, attitudes, an orientation prior."""

    src: np.ndarray  # (N, 3) reconstruction centres
    tgt: np.ndarray  # (N, 3) POS centres, ENU
    sig_pos: np.ndarray  # (N, 3) metres
    R_rec: list[np.ndarray] | None  # reconstruction's R_world_from_cam
    R_pos: list[np.ndarray | None] | None  # POS attitudes (ENU)
    pairs: list[int]  # images whose attitude is used
    sig_att: np.ndarray  # (N,) degrees
    axes: list[int]  # camera axes the prior holds horizontal
    sig_prior: np.ndarray  # (len(axes),) degrees
    height_trend: bool  # a plane in the POS heights is free (their tilt says nothing of the model's)
    yaw_bias: bool = False  # a heading offset common to the POS attitudes is free (a compass's bias)
    sig_level: float | None = None  # "level" prior: the stations' std off a horizontal plane (rec units)
    level_weight: np.ndarray | float = 1.0  # (N,) 1 / sqrt(cameras at the image's station)

    def parts(self, x: np.ndarray, s0: float, R0: np.ndarray) -> tuple:
        """Position (N, 3), attitude (P, 3) and prior (N, len(axes)) residuals of parameters x."""
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        A = self.src - self.src.mean(0)
        r_pos = s0 * np.exp(x[3]) * A @ R.T + x[4:7] - self.tgt
        if self.height_trend:
            d = self.tgt[:, :2] - self.tgt[:, :2].mean(0)
            r_pos[:, 2] -= d @ x[7:9]
        Ra = Rotation.from_rotvec([0.0, 0.0, x[-1]]).as_matrix() @ R if self.yaw_bias else R
        if self.pairs:  # rotvec(R_pos^T Ra R_rec) of every image with an attitude, stacked
            Rp, Rr = self._stacked
            r_att = Rotation.from_matrix(np.swapaxes(Rp, 1, 2) @ Ra @ Rr).as_rotvec()
        else:
            r_att = np.zeros((0, 3))
        n = len(self.src)
        if self.axes:  # the up component of each prior axis: row 2 of R R_rec, columns `axes`
            r_pri = np.einsum("j,njk->nk", R[2], self._rec_all[:, :, self.axes])
        else:
            r_pri = np.zeros((n, 0))
        r_lvl = (A @ R.T)[:, 2] * self.level_weight if self.sig_level else np.zeros(0)
        return r_pos, r_att, r_pri, r_lvl

    @property
    def _stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3, 3) POS attitudes and reconstruction rotations of the images in `pairs` (cached)."""
        key = tuple(self.pairs)
        if getattr(self, "_stack_key", None) != key:
            self._stack = (np.array([self.R_pos[i] for i in key]), np.array([self.R_rec[i] for i in key]))
            self._stack_key = key
        return self._stack

    @property
    def _rec_all(self) -> np.ndarray:
        """(N, 3, 3) reconstruction rotations (cached)."""
        if getattr(self, "_rec_cache", None) is None:
            self._rec_cache = np.array(self.R_rec)
        return self._rec_cache

    def residuals(self, x: np.ndarray, s0: float, R0: np.ndarray) -> np.ndarray:
        r_pos, r_att, r_pri, r_lvl = self.parts(x, s0, R0)
        return np.concatenate(
            [
                (r_pos / self.sig_pos).ravel(),
                (r_att / np.radians(self.sig_att[self.pairs])[:, None]).ravel(),
                (r_pri / np.sin(np.radians(self.sig_prior))).ravel(),
                r_lvl / (self.sig_level or 1.0),
            ]
        )


def _uncertainty(sol) -> dict:
    """1-sigma figures of a least-squares solution (covariance scaled by the reduced chi-square > 1)."""
    dof = max(len(sol.fun) - len(sol.x), 1)
    chi2 = float(np.sum(sol.fun**2) / dof)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * max(chi2, 1.0)
    except np.linalg.LinAlgError:
        cov = np.full((len(sol.x),) * 2, np.inf)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    rot = np.degrees(sd[:3])
    return {
        "rotation_deg": {"east": float(rot[0]), "north": float(rot[1]), "up": float(rot[2])},
        "tilt_deg": float(np.hypot(rot[0], rot[1])),
        "heading_deg": float(rot[2]),
        "scale_rel": float(sd[3]),
        "centroid_m": {"east": float(sd[4]), "north": float(sd[5]), "up": float(sd[6])},
        "reduced_chi2": chi2,
    }


def _noise_used(
    terms: JointTerms, x: np.ndarray, s: float, pairs: list[int], prior: str, source: str, height_trend: bool
) -> dict:
    """The noise a joint fit used and what it found of the POS's biases (refine_joint's `noise`)."""
    return {
        "horizontal_m": float(np.median(terms.sig_pos[:, 0])),
        "vertical_m": float(np.median(terms.sig_pos[:, 2])),
        "position_source": source,
        "attitude_deg": float(np.median(terms.sig_att[pairs])) if pairs else None,
        "attitudes_used": len(pairs),
        "orientation_prior": prior,
        "prior_deg": [float(v) for v in terms.sig_prior] if terms.axes else None,
        "level_std_m": s * terms.sig_level if terms.sig_level else None,
        "height_trend_deg": ([float(np.degrees(np.arctan(v))) for v in x[7:9]] if height_trend else None),
        "attitude_yaw_bias_deg": float(np.degrees(x[-1])) if terms.yaw_bias else None,
    }


def refine_joint(
    src: np.ndarray,
    tgt: np.ndarray,
    init: tuple[float, np.ndarray, np.ndarray],
    pos_std: np.ndarray,
    R_rec: list[np.ndarray] | None = None,
    R_pos: list[np.ndarray | None] | None = None,
    att_std_deg: np.ndarray | None = None,
    conf: dict | None = None,
    default_std: float = 1.0,
    height_trend: bool = False,
    yaw_bias: bool = False,
) -> tuple[float, np.ndarray, np.ndarray, dict, dict]:
    """Weighted least squares of a similarity over centres, attitudes and an orientation prior.

    src, tgt: (N, 3) reconstruction and POS centres; init: (scale, R, t) with tgt ~ scale R src + t;
    pos_std: (N, 3) per-axis position std in metres, NaN where the POS states none (estimated from the
    residuals, pooled over the images: east and north together, up alone; `default_std` where too few
    images); att_std_deg: (N,) likewise for the attitudes. `height_trend`: the POS heights may hold a
    plane of their own (a drifting barometer or GNSS height), so only the attitudes or the prior fix
    the tilt. `yaw_bias`: the POS attitudes may share a heading offset (a consumer drone's compass), so
    only the centres fix the heading. Returns scale, R, t, the noise used and the fit's 1-sigma
    uncertainty.
    """
    conf = {**default_conf, **(conf or {})}
    src, tgt = np.asarray(src, float), np.asarray(tgt, float)
    n = len(src)
    s0, R0, t0 = init
    pairs = [] if R_rec is None or R_pos is None else [i for i, Rp in enumerate(R_pos) if Rp is not None]
    prior = choose_prior(R_rec, len(pairs), conf, src) if R_rec is not None else "none"
    # attitudes far off the initial rotation (a wrong gimbal reading) are left out
    pairs = [
        i for i in pairs if rotation_angle_deg(R_pos[i].T @ R0 @ R_rec[i]) <= conf["attitude_inlier_deg"]
    ]
    pos_stated = np.isfinite(pos_std)
    att_std = np.full(n, np.nan) if att_std_deg is None else np.asarray(att_std_deg, float)
    att_stated = np.isfinite(att_std)
    terms = JointTerms(
        src, tgt, np.where(pos_stated, pos_std, default_std), R_rec, R_pos, pairs,
        np.where(att_stated, att_std, 1.0), _prior_axes(prior),
        prior_spread_deg(R_rec, prior, conf["min_prior_std_deg"]) if R_rec is not None else np.zeros(0),
        height_trend,
        yaw_bias and bool(pairs),
        level_std(src, conf["min_level_std_m"] / max(s0, 1e-12)) if prior == "level" else None,
    )  # fmt: skip
    if prior == "level":
        ids = stations(src)
        terms.level_weight = 1.0 / np.sqrt(np.bincount(ids)[ids])
    est_pos = n >= conf["min_noise_images"] and not pos_stated.all()
    est_att = len(pairs) >= conf["min_noise_images"] and not att_stated[pairs].all()
    x = np.r_[
        np.zeros(3), 0.0, s0 * R0 @ src.mean(0) + t0, np.zeros(2 if height_trend else 0),
        np.zeros(1 if terms.yaw_bias else 0),
    ]  # fmt: skip
    fit = {"loss": "huber", "f_scale": conf["robust_sigmas"], "args": (s0, R0)}
    for _ in range(max(1, conf["noise_iterations"])):
        x = least_squares(terms.residuals, x, **fit).x
        r_pos, r_att, _, _ = terms.parts(x, s0, R0)
        if est_pos:
            h = max(_robust_std(r_pos[:, :2]), conf["min_pos_std_m"])
            v = max(_robust_std(r_pos[:, 2]), conf["min_pos_std_m"])
            terms.sig_pos = np.where(pos_stated, pos_std, np.array([h, h, v]))
        if est_att:
            a = max(float(np.degrees(_robust_std(r_att))), conf["min_att_std_deg"])
            terms.sig_att = np.where(att_stated, terms.sig_att, a)
    sol = least_squares(terms.residuals, x, **fit)
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0
    s = float(s0 * np.exp(sol.x[3]))
    t = sol.x[4:7] - s * R @ src.mean(0)
    source = "stated" if pos_stated.all() else ("estimated" if est_pos else "default")
    noise = _noise_used(terms, sol.x, s, pairs, prior, source, height_trend)
    return s, R, t, noise, _uncertainty(sol)


def _up_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle between the vertical of two rotations ENU_from_reconstruction (their tilts' difference)."""
    return float(np.degrees(np.arccos(np.clip((Ra.T @ [0, 0, 1]) @ (Rb.T @ [0, 0, 1]), -1.0, 1.0))))


def joint_fit(
    src: np.ndarray,
    tgt: np.ndarray,
    init: tuple[float, np.ndarray, np.ndarray],
    pos_std: np.ndarray,
    R_rec, R_pos, att_std_deg, conf: dict, default_std: float,
) -> tuple[float, np.ndarray, np.ndarray, dict, dict]:  # fmt: skip
    """refine_joint over everything; then, where attitudes or a prior fix the tilt on their own, the
    same with a free plane in the POS heights. When the two tilts differ by more than
    conf["height_trend_sigmas"] times the second's std, the heights are tilted against the attitudes
    or camera axes (a systematic GNSS or barometer error, which no per-image noise describes): the
    second fit is kept, and noise["height_trend"] says so. Likewise the heading: with a heading offset
    common to the attitudes left free, a heading that moves by more than that many of its stds means
    the attitudes' headings are biased (a compass): that fit is kept (noise["attitude_yaw"])."""
    args = (src, tgt, init, pos_std, R_rec, R_pos, att_std_deg, conf, default_std)
    full = refine_joint(*args)
    noise = full[3]
    if not (noise["attitudes_used"] >= 3 or noise["orientation_prior"] != "none") or len(src) < 6:
        return full
    free = refine_joint(*args, height_trend=True)
    delta = _up_angle_deg(full[1], free[1])
    bound = conf["height_trend_sigmas"] * max(free[4]["tilt_deg"], 1e-6)
    tilted = delta > bound
    chosen = free if tilted else full
    trend = {
        "tilt_difference_deg": delta,
        "bound_deg": bound,
        "heights_tilted": bool(tilted),
        "trend_deg": free[3]["height_trend_deg"],
    }
    yaw = None
    if noise["attitudes_used"] >= 3 and not condition(tgt)["collinear"]:
        loose = refine_joint(*args, height_trend=tilted, yaw_bias=True)
        diff = abs(float(np.degrees(Rotation.from_matrix(loose[1] @ chosen[1].T).as_rotvec()[2])))
        ybound = conf["height_trend_sigmas"] * max(loose[4]["heading_deg"], 1e-6)
        yaw = {
            "heading_difference_deg": diff,
            "bound_deg": ybound,
            "biased": bool(diff > ybound),
            "bias_deg": loose[3]["attitude_yaw_bias_deg"],
        }
        if diff > ybound:
            chosen = loose
    chosen[3]["height_trend"] = trend
    chosen[3]["attitude_yaw"] = yaw
    return chosen


def _initial_similarity(
    src: np.ndarray, tgt: np.ndarray, pairs: list, cond: dict, max_error: float, conf: dict
) -> tuple[float, np.ndarray, np.ndarray, str, bool]:
    """(scale, R, t, method, from the centres): LO-RANSAC (else least squares) on the centres, or, where
    they are too close to a line and attitudes exist, the rotation from the POS attitudes."""
    sim, res = None, None
    if not (cond["ill_conditioned"] and pairs):
        opts = pycolmap.RANSACOptions(max_error=max_error)
        opts.random_seed = conf["seed"]
        res = pycolmap.estimate_sim3d_robust(src, tgt, opts)
        sim = res["tgt_from_src"] if res is not None else pycolmap.estimate_sim3d(src, tgt)
    if sim is not None:
        s, R, t = float(sim.scale), np.asarray(sim.rotation.matrix()), np.asarray(sim.translation).ravel()
        method = "LO-RANSAC on centres" if res is not None else "least squares on centres"
        return s, R, t, method, True
    if pairs:
        R, n_att = robust_mean_rotation([Rp @ Rr.T for Rr, Rp in pairs], conf["attitude_inlier_deg"])
        s, t = _similarity_from_attitudes(src, tgt, R)
        return (
            s,
            R,
            t,
            f"rotation from {n_att}/{len(pairs)} POS attitudes (centres too close to a line)",
            False,
        )
    raise GeorefError("the similarity estimation failed (degenerate camera centres, no POS attitude)")


def _joint_terms(noise: dict) -> list[str]:
    """What the joint refinement fitted, for the method's description."""
    terms = ["centres"]
    if noise["attitudes_used"]:
        terms.append(f"{noise['attitudes_used']} attitudes")
    if noise["orientation_prior"] != "none":
        terms.append(f"{noise['orientation_prior']} prior")
    if (noise.get("attitude_yaw") or {}).get("biased"):
        bias = noise["attitude_yaw"]["bias_deg"]
        terms.append(f"attitude headings {bias:+.1f} degrees off: heading from the centres")
    if noise.get("height_trend", {}).get("heights_tilted"):
        terms.append(
            f"POS heights tilted {noise['height_trend']['tilt_difference_deg']:.1f} degrees against "
            "them: tilt from them alone"
        )
    return terms


def _residuals(
    geo: Georef,
    names: list[str],
    src: np.ndarray,
    tgt: np.ndarray,
    R_rec: list[np.ndarray] | None,
    R_pos: list[np.ndarray | None] | None,
    max_error: float,
) -> None:
    """The georef's residual and inlier flag per image (within max_error, or horizontally within it and
    vertically within its share of the vertical noise), attitude differences and tilt figures."""
    noise = geo.noise
    res_vec = geo.apply(src) - tgt
    v_error = max_error * noise.get("vertical_m", 1.0) / max(noise.get("horizontal_m", 1.0), 1e-9)
    for i, n in enumerate(names):
        geo.residuals[n] = res_vec[i]
        geo.inliers[n] = bool(
            np.linalg.norm(res_vec[i]) <= max_error
            or (np.linalg.norm(res_vec[i][:2]) <= max_error and abs(res_vec[i][2]) <= v_error)
        )
    if R_pos is not None:
        for n, Rr, Rp in zip(names, R_rec or [], R_pos or [], strict=True):
            if Rp is not None:
                geo.attitude_deg[n] = rotation_angle_deg(Rp.T @ (geo.R @ Rr))
    geo.levels = tilt_figures(geo.apply(src), [geo.R @ Rr for Rr in R_rec] if R_rec is not None else None)


def estimate(
    names: list[str],
    src: np.ndarray,
    tgt: np.ndarray,
    sigma: float,
    R_rec: list[np.ndarray] | None = None,
    R_pos: list[np.ndarray | None] | None = None,
    conf: dict | None = None,
    pos_std: np.ndarray | None = None,
    att_std_deg: np.ndarray | None = None,
) -> Georef:
    """Similarity tgt_from_src from camera centres `src` (reconstruction) to `tgt` (POS, ENU metres).

    `R_rec` are the reconstruction's R_world_from_cam and `R_pos` the POS attitudes (or None), used for
    the rotation (joint refinement; the initial one where the centres are collinear), the orientation
    prior and the attitude residuals. `pos_std` (N, 3) and `att_std_deg` (N,): the stated stds, NaN
    where the POS states none (then estimated from the residuals); by default `sigma` for every axis.
    """
    conf = {**default_conf, **(conf or {})}
    src, tgt = np.asarray(src, float), np.asarray(tgt, float)
    if len(names) < conf["min_images"]:
        raise GeorefError(
            f"{len(names)} registered images with POS; georeferencing needs {conf['min_images']}"
        )
    cond = condition(tgt, sigma, conf)
    max_error = max(conf["max_error_sigmas"] * sigma, conf["min_max_error"])
    cond["max_error_m"] = max_error
    pairs = (
        []
        if R_rec is None or R_pos is None
        else [(a, b) for a, b in zip(R_rec, R_pos, strict=True) if b is not None]
    )
    s, R, t, method, centred = _initial_similarity(src, tgt, pairs, cond, max_error, conf)
    noise, unc = {}, {}
    if conf["joint"]:
        std = np.full((len(src), 3), float(sigma)) if pos_std is None else np.asarray(pos_std, float)
        s, R, t, noise, unc = joint_fit(
            src, tgt, (s, R, t), std, R_rec, R_pos, att_std_deg, conf, float(sigma)
        )
        method += ", joint refinement (" + ", ".join(_joint_terms(noise)) + ")"
        if noise["position_source"] != "stated":
            max_error = max(conf["max_error_sigmas"] * noise["horizontal_m"], conf["min_max_error"])
            cond["max_error_m"] = max_error
    fixed = noise.get("attitudes_used") or noise.get("orientation_prior", "none") != "none"
    if cond["ill_conditioned"] and centred and not fixed:
        method += " (ill-conditioned: centres close to a line, no POS attitude)"
        logger.warning(
            "camera centres are nearly collinear and the POS has no attitude: the rotation about "
            "the flight line is uncertain by about %.1f degrees",
            cond["rotation_uncertainty_deg"],
        )
    geo = Georef(s, R, t, method, cond, noise=noise, uncertainty=unc)
    _residuals(geo, names, src, tgt, R_rec, R_pos if pairs else None, max_error)
    if cond["coplanar"]:
        logger.info(
            "camera centres are nearly coplanar (one flight height): the similarity is still determined"
        )
    return geo


def georeference(
    rec: pycolmap.Reconstruction,
    records: dict[str, PosRecord],
    frame: LocalFrame,
    sigma: float,
    conf: dict | None = None,
) -> Georef:
    """Estimate the similarity for a reconstruction and apply it in place (the model becomes local ENU).

    The records' stated stds weight the joint refinement (`sigma` where they state none and the noise
    cannot be estimated); their attitudes are taken from the ENU frame at each image to `frame`'s."""
    names, src, tgt, R_rec, R_pos, pos_std, att_std = [], [], [], [], [], [], []
    for img in rec.images.values():
        if not img.has_pose or img.name not in records:
            continue
        r = records[img.name]
        names.append(img.name)
        src.append(img.projection_center())
        tgt.append(frame.from_wgs84(r.lat, r.lon, r.h)[0])
        R_rec.append(img.cam_from_world().rotation.matrix().T)
        Rp = r.R_world_from_cam
        R_pos.append(None if Rp is None else frame.rotation_to_enu_at(r.lat, r.lon).T @ Rp)
        nan = float("nan")
        pos_std.append([r.std_xy or nan, r.std_xy or nan, r.std_z or r.std_xy or nan])
        att_std.append(r.std_att or nan)
    geo = estimate(
        names,
        np.array(src).reshape(-1, 3),
        np.array(tgt).reshape(-1, 3),
        sigma,
        R_rec,
        R_pos,
        conf,
        pos_std=np.array(pos_std, float).reshape(-1, 3),
        att_std_deg=np.array(att_std, float),
    )
    rec.transform(geo.sim3d)
    return geo


def _stats(values: list[float]) -> dict:
    if not values:
        return {"mean": None, "median": None, "max": None, "rmse": None}
    a = np.asarray(values, float)
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "max": float(a.max()),
        "rmse": float(np.sqrt(np.mean(a**2))),
    }


def status(geo: Georef, conf: dict | None = None) -> tuple[str, list[str]]:
    """("ok" | "suspect" | "failed", reasons) of a georeferencing, from its inliers and residuals."""
    conf = {**default_conf, **(conf or {})}
    n, n_in = len(geo.inliers), int(sum(geo.inliers.values()))
    thr = float(geo.condition.get("max_error_m", conf["min_max_error"]))
    norms = [float(np.linalg.norm(v)) for v in geo.residuals.values()]
    reasons = []
    if n_in < conf["min_images"]:
        reasons.append(f"only {n_in} of {n} cameras lie within {thr:.1f} m of their POS")
        return "failed", reasons
    if n_in < conf["min_inlier_ratio"] * n:
        reasons.append(f"only {n_in} of {n} cameras lie within {thr:.1f} m of their POS")
    if norms and float(np.mean(norms)) > thr:
        reasons.append(f"mean residual {np.mean(norms):.2f} m is above the inlier threshold {thr:.1f} m")
    att = list(geo.attitude_deg.values())
    if att and float(np.median(att)) > conf["attitude_inlier_deg"]:
        reasons.append(f"camera attitudes are {np.median(att):.1f} degrees off the POS (median)")
    unc = geo.uncertainty or {}
    if unc.get("tilt_deg") is not None and unc["tilt_deg"] > conf["max_tilt_std_deg"]:
        noise = geo.noise or {}
        reasons.append(
            f"the model's tilt is uncertain by {unc['tilt_deg']:.1f} degrees (1 sigma; POS noise "
            f"{noise.get('horizontal_m', float('nan')):.1f} m horizontal, "
            f"{noise.get('vertical_m', float('nan')):.1f} m vertical)"
        )
    if "ill-conditioned" in geo.method:
        reasons.append(
            "camera centres close to a line and no POS attitude: the rotation about it is uncertain by "
            f"{geo.condition['rotation_uncertainty_deg']:.1f} degrees"
        )
    return ("suspect" if reasons else "ok"), reasons


def summary(geo: Georef, conf: dict | None = None) -> dict:
    """Residual statistics (metres, degrees) and status of a georeferencing."""
    norms = [float(np.linalg.norm(v)) for v in geo.residuals.values()]
    state, reasons = status(geo, conf)
    return {
        "status": state,
        "reasons": reasons,
        "num_images": len(geo.residuals),
        "num_inliers": int(sum(geo.inliers.values())),
        "residual_m": _stats(norms),
        "horizontal_m": _stats([float(np.linalg.norm(v[:2])) for v in geo.residuals.values()]),
        "vertical_m": _stats([float(abs(v[2])) for v in geo.residuals.values()]),
        "attitude_deg": _stats(list(geo.attitude_deg.values())),
        "pos_noise": geo.noise or None,
        "uncertainty": geo.uncertainty or None,
        "levels": geo.levels or None,
        "suspect": state != "ok",
    }


def failed_summary(reason: str) -> dict:
    """The summary of a georeferencing that could not be estimated at all."""
    return {
        "status": "failed",
        "reasons": [reason],
        "num_images": 0,
        "num_inliers": 0,
        **{k: _stats([]) for k in ("residual_m", "horizontal_m", "vertical_m", "attitude_deg")},
        "suspect": True,
    }


def read_georef_frame(path: str | Path) -> LocalFrame:
    """The local ENU frame (origin) of a georef.json that write_georef wrote."""
    f = json.loads(Path(path).read_text())["frame"]
    return LocalFrame(float(f["lat0"]), float(f["lon0"]), float(f["h0"]))


def write_georef(
    path: str | Path,
    geo: Georef | None,
    frame: LocalFrame,
    crs: dict | None = None,
    summary_doc: dict | None = None,
) -> Path:
    """georef.json: frame origin, similarity (ENU from reconstruction), conditioning, status, residuals per
    image; `crs`: the POS input CRS and the output CRS (`{"pos": ..., "output": ..., "files": [...]}`).
    Without `geo` (the estimation failed): the frame, the CRSs and `summary_doc` (status, reasons)."""
    head = {
        "frame": {"type": "ENU", "lat0": frame.lat0, "lon0": frame.lon0, "h0": frame.h0},
        "crs": crs or {"pos": None, "output": None},
    }
    path = Path(path)
    if geo is None:
        path.write_text(json.dumps({**head, "summary": summary_doc}, indent=1))
        return path
    q = pycolmap.Rotation3d(geo.R).quat  # xyzw
    doc = {
        **head,
        "sim3": {
            "scale": geo.scale,
            "rotation": geo.R.tolist(),
            "quaternion_xyzw": [float(v) for v in q],
            "translation": geo.t.tolist(),
            "direction": "enu_from_reconstruction: X_enu = scale * R @ X_rec + t",
        },
        "method": geo.method,
        "condition": geo.condition,
        "summary": summary_doc or summary(geo),
        "images": {
            n: {
                "residual_enu_m": [float(x) for x in v],
                "residual_m": float(np.linalg.norm(v)),
                "inlier": geo.inliers[n],
                **({"attitude_deg": geo.attitude_deg[n]} if n in geo.attitude_deg else {}),
            }
            for n, v in sorted(geo.residuals.items())
        },
    }
    path.write_text(json.dumps(doc, indent=1))
    return path
