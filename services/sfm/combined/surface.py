"""A ground-ground pair checked against the aerial surface: do its matches fit the scene?

An essential matrix accepts two images of different walls that carry the same texture (repeated facades,
the same shop front twice), and where the POS noise is as large as the baseline neither the relative
rotation nor the baseline's direction can tell. The aerial model can: the first image's inlier pixels,
lifted onto the aerial surface (the plane proxy of the aerial model's points, services.views.PlaneProxy)
from a pose of it tied to the aerial images (the reducer's accepted PnP pose), are where that camera
sees them; the second image's pixels of the same matches must then place the second camera (PnP) where
its POS says it is, within what the POS allows. Matches between different walls place it elsewhere, or
nowhere (few PnP inliers).

Lifted from a POS pose instead, the check cannot tell: on `isprs` (ground POS noise 2.5 m horizontal,
4 m vertical, 2 degrees) it refused the 4 false pairs it judged and 5 of the 6 true ones
(docs/measurements.md), so a pair of which neither image has an aerial-tied pose is not judged.

    check = SurfaceCheck(PlaneProxy.from_model(aerial_dir / "sparse"), camera, conf)
    rec = check(name0, kp0_inliers, kp1_inliers, pose0, prior1, std0, std1)   # rec["accepted"]
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose

PosStd = tuple[float, float, float]  # (horizontal m, vertical m, attitude deg)

default_conf: dict[str, Any] = {
    "enabled": True,
    "enforce": True,  # False: the check is recorded in the pair's report, the pair kept (to measure it)
    "min_points": 12,  # inliers with a surface behind them needed to judge (fewer: not judged, kept)
    "min_inlier_ratio": 0.5,  # of those, the share the second camera's PnP pose must explain
    "ransac_px": 4.0,
    "prior_sigmas": 3.0,  # the POS noise allowed between where PnP puts the second camera and its POS
    "min_offset_m": 1.0,  # at least this much is always allowed
    "seed": 0,
}


class SurfaceCheck:
    """The check of a pair (see the module), with each image's surface depth cached by name."""

    def __init__(self, proxy: Any, camera: Camera, conf: dict[str, Any] | None = None):
        self.proxy, self.camera = proxy, camera
        self.conf = {**default_conf, **(conf or {})}
        self._depth: dict[str, np.ndarray] = {}

    def depth(self, name: str, pose: Pose) -> np.ndarray:
        """The aerial surface's z-depth (H, W) seen from `name`'s POS pose (0: no surface)."""
        if name not in self._depth:
            self._depth[name] = np.asarray(self.proxy.depth(self.camera, pose), np.float64)
        return self._depth[name]

    def __call__(
        self,
        name0: str,
        p0: np.ndarray,
        p1: np.ndarray,
        prior0: Pose,
        prior1: Pose,
        std0: PosStd,
        std1: PosStd,
    ) -> dict[str, Any]:
        """{"accepted", "reason", "points", "pnp_inliers", "offset_m", "limit_m"} for the inlier pixels
        p0 of image name0 (N, 2) and p1 of the other image (N, 2)."""
        c = self.conf
        d = self.depth(name0, prior0)
        h, w = d.shape
        u = np.clip(np.floor(p0[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.floor(p0[:, 1]).astype(int), 0, h - 1)
        z = d[v, u]
        keep = z > 0
        rec: dict[str, Any] = {"points": int(keep.sum()), "accepted": True}
        if keep.sum() < int(c["min_points"]):
            rec["reason"] = (
                f"{int(keep.sum())} matches on the aerial surface (< {c['min_points']}): not judged"
            )
            return rec
        X = prior0.unproject(np.asarray(self.camera.K, float), p0[keep], z[keep])
        opts = pycolmap.AbsolutePoseEstimationOptions()
        opts.ransac.max_error = float(c["ransac_px"])
        opts.ransac.random_seed = int(c["seed"])
        opts.ransac.min_inlier_ratio = 0.05
        try:
            out = pycolmap.estimate_and_refine_absolute_pose(
                np.ascontiguousarray(p1[keep], np.float64),
                np.ascontiguousarray(X, np.float64),
                self.camera.to_pycolmap(1),
                opts,
            )
        except Exception:  # pycolmap raises on degenerate input
            out = None
        if out is None:
            rec.update(accepted=False, pnp_inliers=0, reason="its matches place the second camera nowhere")
            return rec
        m = np.asarray(out["cam_from_world"].matrix())
        center = -m[:, :3].T @ m[:, 3]
        n_in = int(out["num_inliers"])
        offset = float(np.linalg.norm(center - prior1.center))
        # both POS errors, and the first camera's attitude error swinging its rays at the surface's depth
        k = float(c["prior_sigmas"])
        spread = math.sqrt(2.0 * (std0[0] ** 2 + std1[0] ** 2) + std0[1] ** 2 + std1[1] ** 2)
        swing = float(np.median(z[keep])) * math.sin(math.radians(std0[2]))
        limit = max(k * math.hypot(spread, swing), float(c["min_offset_m"]))
        rec.update(pnp_inliers=n_in, offset_m=round(offset, 2), limit_m=round(limit, 2))
        reasons = []
        if n_in < float(c["min_inlier_ratio"]) * keep.sum():
            reasons.append(f"its matches fit one pose of the second camera for {n_in} of {int(keep.sum())}")
        if offset > limit:
            reasons.append(f"they place the second camera {offset:.1f} m from its POS (> {limit:.1f})")
        if reasons:
            rec.update(accepted=False, reason="; ".join(reasons))
        else:
            rec["reason"] = "ok"
        return rec
