"""Colour of a rendered view from the full-resolution aerial images, through the 3DGS depth.

A 3DGS trained on 400-640 px images on the CPU gets the scene's geometry roughly right but smears its
texture at the intermediate views, which stand two to four times closer to the facades than the aerial
cameras. The source images hold that texture at their full resolution. For each pixel of a view this
takes the 3DGS's depth, lifts it to a 3D point, finds the aerial images that see that point (the point
lies in front of the camera, inside its image and no nearer surface of the 3DGS's depth at that camera
hides it) and samples the colour of the best of them (the smallest angle between the view's ray and the
source's ray, the finest ground sampling distance), at the image-pyramid level that matches the view's
pixel size. Pixels no source sees keep the 3DGS's colour. This is unstructured lumigraph rendering with
one source per pixel (Buehler et al. 2001), the 3DGS standing in for the geometric proxy.

    src = SourceImages(rec_dir, image_dir)          # an aerial COLMAP model and its image folder
    rgb = src.colour(camera, pose, depth, rgb_3dgs, depth_fn)

A render pixel coloured this way shows what the chosen aerial image shows along its own ray: when the
3DGS's depth is off, the texture shifts in the view, but a match of the view with a ground image still
stands for a match with that aerial image's pixel, which is what the reducer transfers.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose

logger = logging.getLogger("midview.views.source")

confs: dict[str, dict[str, Any]] = {
    "default": {
        "visibility_rel": 0.05,  # a source sees a point when its 3DGS depth there is within 5% (+ abs)
        "visibility_abs_m": 0.3,
        "depth_width": 480,  # width of the sources' 3DGS depth maps (visibility only)
        "resolution_weight_deg": 10.0,  # penalty per doubling of the source's ground sampling distance
        "max_angle_deg": 75.0,  # a source more than this off the view's ray is not used
        "blend_deg": 0.0,  # >0: soft blend of the two best sources within this penalty difference
        "cache_images": 16,  # full-resolution source images held in memory
    },
}

DepthFn = Callable[[Camera, Pose], np.ndarray]


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray, cols: int = 4096) -> np.ndarray:
    """Bilinear samples (N, C) of img at OpenCV pixel coordinates (N,) (remap wants 2D maps of at most
    32767 columns: the points go in rows of `cols`)."""
    n = len(x)
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(
        img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    return out.reshape(rows * cols, -1)[:n]


class SourceImages:
    """The aerial images of a COLMAP model (full resolution, lazily loaded) and their 3DGS depth maps."""

    def __init__(self, rec_dir: str | Path, image_dir: str | Path, conf: dict | None = None):
        self.conf = {**confs["default"], **(conf or {})}
        self.image_dir = Path(image_dir)
        rec = pycolmap.Reconstruction(str(rec_dir))
        self._rec = rec  # the cameras below are references into it
        self.sources: list[dict] = []
        for img in sorted(rec.images.values(), key=lambda i: i.name):
            if not img.has_pose:
                continue
            m = img.cam_from_world().matrix()
            self.sources.append(
                {
                    "name": img.name,
                    "camera": img.camera,
                    "pose": Pose(m[:, :3].copy(), m[:, 3].copy()),
                }
            )
        self._pyramids: OrderedDict[str, list[np.ndarray]] = OrderedDict()
        self._depths: dict[str, tuple[np.ndarray, float]] = {}

    # -- cached inputs ---------------------------------------------------------------------------
    def pyramid(self, name: str) -> list[np.ndarray]:
        """RGB float32 levels of a source image: full resolution, then halved until 256 px."""
        if name in self._pyramids:
            self._pyramids.move_to_end(name)
            return self._pyramids[name]
        bgr = cv2.imread(str(self.image_dir / name), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(f"source image {self.image_dir / name} is missing or unreadable")
        levels = [cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32)]
        while min(levels[-1].shape[:2]) > 256:
            levels.append(cv2.pyrDown(levels[-1]))
        self._pyramids[name] = levels
        while len(self._pyramids) > int(self.conf["cache_images"]):
            self._pyramids.popitem(last=False)
        return levels

    def depth(self, src: dict, depth_fn: DepthFn) -> tuple[np.ndarray, float]:
        """(3DGS z-depth at the source camera, reduced; its scale against the full image)."""
        if src["name"] not in self._depths:
            cam = src["camera"]
            s = min(1.0, float(self.conf["depth_width"]) / cam.width)
            K = cam.calibration_matrix()
            small = Camera(
                "PINHOLE",
                max(1, round(cam.width * s)),
                max(1, round(cam.height * s)),
                [K[0, 0] * s, K[1, 1] * s, K[0, 2] * s, K[1, 2] * s],
            )
            self._depths[src["name"]] = (np.asarray(depth_fn(small, src["pose"]), np.float32), s)
        return self._depths[src["name"]]

    # -- colour ----------------------------------------------------------------------------------
    def colour(
        self,
        camera: Camera,
        pose: Pose,
        depth: np.ndarray,
        fallback: np.ndarray,
        depth_fn: DepthFn,
    ) -> tuple[np.ndarray, dict]:
        """RGB uint8 (H, W, 3) of the view: each pixel with depth > 0 from its best visible source,
        the others (and those no source sees) from `fallback` (uint8 (H, W, 3)). Returns the image and
        figures (fraction of pixels coloured from sources, sources used)."""
        c = self.conf
        H, W = depth.shape
        vi, ui = np.nonzero(depth > 0)
        out = fallback.astype(np.float32).copy()
        if len(vi) == 0:
            return fallback, {"source_fraction": 0.0, "sources_used": 0}
        K = camera.K
        uv_v = np.stack([ui + 0.5, vi + 0.5], 1).astype(np.float64)  # pixel centres, COLMAP convention
        X = pose.unproject(K, uv_v, depth[vi, ui].astype(float))
        C = pose.center
        ray_v = X - C
        dist_v = np.linalg.norm(ray_v, axis=1)
        ray_v /= dist_v[:, None]
        gsd_v = depth[vi, ui] / K[0, 0]  # metres per view pixel (at the point, along the axis)
        n = len(X)
        best = np.full(n, np.inf)
        second = np.full(n, np.inf)
        best_i = np.full(n, -1, np.int32)
        second_i = np.full(n, -1, np.int32)
        samples: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        cos_max = np.cos(np.radians(float(c["max_angle_deg"])))
        for si, src in enumerate(self.sources):
            sp: Pose = src["pose"]
            cam = src["camera"]
            Xc = X @ sp.R.T + sp.t
            z = Xc[:, 2]
            front = z > 1e-3
            if not front.any():
                continue
            idx = np.nonzero(front)[0]
            uv = cam.img_from_cam(Xc[idx])
            ok = np.all(np.isfinite(uv), axis=1)
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height - 1)
            idx, uv = idx[ok], uv[ok]
            if len(idx) < 0.002 * n:
                continue
            ray_s = X[idx] - sp.center
            ray_s /= np.linalg.norm(ray_s, axis=1, keepdims=True)
            cosang = np.einsum("ij,ij->i", ray_s, ray_v[idx])
            ok = cosang >= cos_max
            idx, uv, cosang = idx[ok], uv[ok], cosang[ok]
            if len(idx) == 0:
                continue
            dmap, s = self.depth(src, depth_fn)
            du = np.clip((uv[:, 0] * s).astype(int), 0, dmap.shape[1] - 1)
            dv = np.clip((uv[:, 1] * s).astype(int), 0, dmap.shape[0] - 1)
            ds = dmap[dv, du]
            zs = z[idx]
            vis = (ds > 0) & (zs <= ds * (1.0 + float(c["visibility_rel"])) + float(c["visibility_abs_m"]))
            idx, uv, cosang, zs = idx[vis], uv[vis], cosang[vis], zs[vis]
            if len(idx) == 0:
                continue
            f_s = float(cam.mean_focal_length())
            gsd_s = zs / f_s
            angle = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
            penalty = angle + float(c["resolution_weight_deg"]) * np.log2(np.maximum(gsd_s, 1e-6))
            # keep the two best sources per pixel
            better = penalty < best[idx]
            mid = ~better & (penalty < second[idx])
            sub = idx[better]
            second[sub], second_i[sub] = best[sub], best_i[sub]
            best[sub], best_i[sub] = penalty[better], si
            sub2 = idx[mid]
            second[sub2], second_i[sub2] = penalty[mid], si
            samples[si] = (idx, uv, gsd_s / gsd_v[idx])
        colour = np.zeros((n, 3), np.float32)
        weight = np.zeros(n, np.float32)
        blend = float(c["blend_deg"])
        used = 0
        for si, (idx, uv, ratio) in samples.items():
            w = np.where(best_i[idx] == si, 1.0, 0.0)
            if blend > 0:
                d = best[idx] - second[idx]
                w_second = np.clip(1.0 - (-d) / blend, 0.0, 1.0) * 0.5
                w = np.where(best_i[idx] == si, 1.0, np.where(second_i[idx] == si, w_second, 0.0))
            take = w > 0
            if not take.any():
                continue
            used += int((best_i[idx] == si).any())
            idx, uv, ratio, w = idx[take], uv[take], ratio[take], w[take]
            levels = self.pyramid(self.sources[si]["name"])
            # source pixels per view pixel: 1/ratio; sample the level where that is about 1
            lvl = int(np.clip(np.floor(np.log2(max(np.median(1.0 / ratio), 1.0))), 0, len(levels) - 1))
            img = levels[lvl]
            scale = 1.0 / (2**lvl)
            mx = (uv[:, 0] * scale - 0.5).astype(np.float32)  # COLMAP pixel coordinates -> OpenCV's
            my = (uv[:, 1] * scale - 0.5).astype(np.float32)
            val = _sample(img, mx, my)
            colour[idx] += w[:, None] * val
            weight[idx] += w
        has = weight > 0
        out[vi[has], ui[has]] = colour[has] / weight[has, None]
        rgb = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return rgb, {"source_fraction": float(has.sum() / (H * W)), "sources_used": used}
