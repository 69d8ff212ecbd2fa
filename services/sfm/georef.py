"""Georeferencing: a robust similarity from reconstructed camera centres to POS positions (local ENU).

The similarity is estimated with pycolmap's LO-RANSAC (`estimate_sim3d_robust`), with an inlier
threshold scaled to the POS standard deviation. Its conditioning is checked first: camera centres on
one line (a single flight line, or a few stations along one line) leave the rotation about that line
free, or fixed only by deviations from the line comparable to the POS noise: the rotation uncertainty
is about sigma / s2 radians (s2: second singular value of the centred positions). When it is too
large and the POS has attitudes, the rotation is taken from them (robust chordal mean of
R_pos @ R_rec^T) and only the scale and translation from the centres; without attitudes the result is
flagged ill-conditioned. Camera centres in one plane (a survey flown at one height) are fine: two
independent directions fix a rotation.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

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
    counts = [sum(_rotation_angle_deg(a.T @ b) <= inlier_deg for b in Rs) for a in Rs]
    best = Rs[int(np.argmax(counts))]
    inl = [b for b in Rs if _rotation_angle_deg(best.T @ b) <= inlier_deg]
    return mean_rotation(inl), len(inl)


def _rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _similarity_from_attitudes(src: np.ndarray, tgt: np.ndarray, R: np.ndarray) -> tuple[float, np.ndarray]:
    """Scale and translation given the rotation (least squares on the centres)."""
    a, b = src - src.mean(0), tgt - tgt.mean(0)
    ra = a @ R.T
    s = float(np.sum(ra * b) / max(np.sum(ra * ra), 1e-12))
    return s, tgt.mean(0) - s * R @ src.mean(0)


def estimate(
    names: list[str],
    src: np.ndarray,
    tgt: np.ndarray,
    sigma: float,
    R_rec: list[np.ndarray] | None = None,
    R_pos: list[np.ndarray | None] | None = None,
    conf: dict | None = None,
) -> Georef:
    """Similarity tgt_from_src from camera centres `src` (reconstruction) to `tgt` (POS, ENU metres).

    `R_rec` are the reconstruction's R_world_from_cam and `R_pos` the POS attitudes (or None), used for
    the attitude residuals and for the rotation when the centres are collinear.
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
    sim, res = None, None
    if not (cond["ill_conditioned"] and pairs):
        opts = pycolmap.RANSACOptions(max_error=max_error)
        opts.random_seed = conf["seed"]
        res = pycolmap.estimate_sim3d_robust(src, tgt, opts)
        sim = res["tgt_from_src"] if res is not None else pycolmap.estimate_sim3d(src, tgt)
    if sim is not None:
        s, R, t = float(sim.scale), np.asarray(sim.rotation.matrix()), np.asarray(sim.translation).ravel()
        method = "LO-RANSAC on centres" if res is not None else "least squares on centres"
        if cond["ill_conditioned"]:
            method += " (ill-conditioned: centres close to a line, no POS attitude)"
            logger.warning(
                "camera centres are nearly collinear and the POS has no attitude: the rotation about "
                "the flight line is uncertain by about %.1f degrees",
                cond["rotation_uncertainty_deg"],
            )
    elif pairs:
        R, n_att = robust_mean_rotation([Rp @ Rr.T for Rr, Rp in pairs], conf["attitude_inlier_deg"])
        s, t = _similarity_from_attitudes(src, tgt, R)
        method = f"rotation from {n_att}/{len(pairs)} POS attitudes (centres too close to a line)"
    else:
        raise GeorefError("the similarity estimation failed (degenerate camera centres, no POS attitude)")
    geo = Georef(s, R, t, method, cond)
    res_vec = geo.apply(src) - tgt
    for i, n in enumerate(names):
        geo.residuals[n] = res_vec[i]
        geo.inliers[n] = bool(np.linalg.norm(res_vec[i]) <= max_error)
    if pairs:
        for n, Rr, Rp in zip(names, R_rec or [], R_pos or [], strict=True):
            if Rp is not None:
                geo.attitude_deg[n] = _rotation_angle_deg(Rp.T @ (R @ Rr))
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
    """Estimate the similarity for a reconstruction and apply it in place (the model becomes local ENU)."""
    names, src, tgt, R_rec, R_pos = [], [], [], [], []
    for img in rec.images.values():
        if not img.has_pose or img.name not in records:
            continue
        r = records[img.name]
        names.append(img.name)
        src.append(img.projection_center())
        tgt.append(frame.from_wgs84(r.lat, r.lon, r.h)[0])
        R_rec.append(img.cam_from_world().rotation.matrix().T)
        R_pos.append(r.R_world_from_cam)
    geo = estimate(
        names, np.array(src).reshape(-1, 3), np.array(tgt).reshape(-1, 3), sigma, R_rec, R_pos, conf
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
