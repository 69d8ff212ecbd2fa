"""Colour of a rendered view from the full-resolution aerial images, through the view's depth.

A 3DGS trained on 400-640 px images on the CPU smears its texture at the intermediate views, which stand
two to four times closer to the facades than the aerial cameras. The source images hold that texture at
their full resolution. For each pixel of a view this takes its depth (the plane proxy's where it has one,
services.views.proxy, else the 3DGS's), lifts it to a 3D point, finds the aerial images that see that
point (the point lies in front of the camera, inside its image and no nearer surface of the 3DGS's depth
at that camera hides it) and samples the colour of the best of them (the smallest angle between the
view's ray and the source's ray, the finest ground sampling distance), at the image-pyramid level that
matches the view's pixel size. The two best sources must agree on a point's colour; pixels where they do
not, or that no source sees, keep the 3DGS's colour. This is unstructured lumigraph rendering with one
source per pixel (Buehler et al. 2001).

    src = SourceImages("sfm/sparse", "images")          # an aerial COLMAP model and its image folder
    rgb, depth, stats = src.colour(camera, pose, depth, rgb_3dgs, depth_fn)

A render pixel coloured this way shows what the chosen aerial image shows along its own ray: where the
depth is off, the texture shifts in the view, but a match of the view with a ground image still stands
for a match with that aerial image's pixel, which is what the reducer transfers.
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
        "max_angle_deg": 75.0,  # a source more than this off the view's ray is not used ...
        # ... unless the view's depth is planar there (its normal known from the depth map) and the
        # source sees it at most this far from its normal: a plane's colour is where any camera that
        # sees it puts it, so a view at street level looking up at a facade the aerial images see from
        # above (ray angles of 100-140 degrees) takes its colour from them (0 or None: the ray angle only)
        "max_incidence_deg": 75.0,
        "normal_tolerance": 0.01,  # a pixel's normal is known where the surface is planar (surface_normals)
        # the two best sources must agree on a point's colour (mean absolute difference over 7x7 pixels
        # below this many grey levels): where the 3DGS's depth is off they see different surfaces
        "consistency": 12.0,
        # the free-space test (seen_through): a point lies in front of a source's surface when nearer than
        # its depth there by more than free_space_sigmas x that depth map's own relative error (the median
        # over the source's sparse points, at least free_space_min_rel), + free_space_abs_m
        "free_space_sigmas": 3.0,
        "free_space_min_rel": 0.005,
        "free_space_abs_m": 0.1,
        "cache_mb": 1500,  # source image pyramids held in memory (uint8)
    },
}

DepthFn = Callable[[Camera, Pose], np.ndarray]


def _two_best(n: int, scored: list[tuple[int, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The best and second best (lowest penalty) source of each of n points, -1 where none, from
    (source index, point indices, penalties) per source."""
    best = np.full(n, np.inf, np.float32)
    second = np.full(n, np.inf, np.float32)
    best_i = np.full(n, -1, np.int32)
    second_i = np.full(n, -1, np.int32)
    for si, idx, pen in scored:
        win = pen < best[idx]
        mid = ~win & (pen < second[idx])
        w, m = idx[win], idx[mid]
        second[w], second_i[w] = best[w], best_i[w]
        best[w], best_i[w] = pen[win], si
        second[m], second_i[m] = pen[mid], si
    return best_i, second_i


def pixel_points(camera: Camera, pose: Pose, depth: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) float64 of the pixel centres (COLMAP convention) of a z-depth map (H, W)."""
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
    return pose.unproject(camera.K, uv, depth.astype(np.float64).ravel()).reshape(H, W, 3)


def surface_normals(
    camera: Camera, pose: Pose, depth: np.ndarray, tolerance: float, points: np.ndarray | None = None
) -> np.ndarray:
    """Unit normals (H, W, 3) float32 in the world frame of the surface a z-depth map (H, W) shows,
    facing its camera; NaN where the surface is not locally planar. A plane's inverse depth is affine in
    the pixel coordinates, at any angle: a pixel is planar where its own and its four neighbours' depths
    exist and the second difference of the inverse depth along each axis is within `tolerance` of its
    inverse depth (not at edges, the image border or where there is no depth). `points`: the map's
    pixel_points where the caller has them."""
    H, W = depth.shape
    out = np.full((H, W, 3), np.nan, np.float32)
    if H < 3 or W < 3:
        return out
    d = depth.astype(np.float64)
    inv = np.where(d > 0, 1.0 / np.maximum(d, 1e-12), np.nan)
    c = inv[1:-1, 1:-1]
    with np.errstate(invalid="ignore"):  # NaN (no depth) fails the test
        planar = (np.abs(inv[1:-1, :-2] + inv[1:-1, 2:] - 2 * c) <= tolerance * c) & (
            np.abs(inv[:-2, 1:-1] + inv[2:, 1:-1] - 2 * c) <= tolerance * c
        )
    X = pixel_points(camera, pose, depth) if points is None else points
    n = np.cross(X[1:-1, 2:] - X[1:-1, :-2], X[2:, 1:-1] - X[:-2, 1:-1])
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-12)
    n *= np.where(np.einsum("ijk,ijk->ij", n, pose.center - X[1:-1, 1:-1]) < 0, -1.0, 1.0)[..., None]
    out[1:-1, 1:-1] = np.where(planar[..., None], n, np.nan)
    return out


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray, cols: int = 4096) -> np.ndarray:
    """Bilinear samples (N, C) of img at OpenCV pixel coordinates (N,) (remap wants 2D maps of at most
    32767 columns: the points go in rows of `cols`)."""
    n = len(x)
    rows = max(1, -(-n // cols))
    mx = np.full(rows * cols, -1e4, np.float32)  # padding samples fall outside: constant, unused
    my = np.full(rows * cols, -1e4, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(
        img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.reshape(rows * cols, -1)[:n]


class SourceImages:
    """The aerial images of a COLMAP model (full resolution, lazily loaded) and their 3DGS depth maps."""

    def __init__(
        self, model: str | Path | pycolmap.Reconstruction, image_dir: str | Path, conf: dict | None = None
    ):
        """`model`: the aerial COLMAP model, a folder or a loaded Reconstruction."""
        self.conf = {**confs["default"], **(conf or {})}
        self.image_dir = Path(image_dir)
        rec = model if isinstance(model, pycolmap.Reconstruction) else pycolmap.Reconstruction(str(model))
        self._rec = rec  # the cameras below are references into it
        self.sources: list[dict] = []
        for img in sorted(rec.images.values(), key=lambda i: i.name):
            if not img.has_pose:
                continue
            m = img.cam_from_world().matrix()
            cam = img.camera
            pinhole = None
            extra = np.asarray(cam.params)[list(cam.extra_params_idxs())]
            if not np.any(extra):  # no distortion (PINHOLE, or a radial model with k = 0)
                K = cam.calibration_matrix()
                pinhole = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
            self.sources.append(
                {
                    "name": img.name,
                    "camera": cam,
                    "pose": Pose(m[:, :3].copy(), m[:, 3].copy()),
                    "pinhole": pinhole,
                    "image_id": img.image_id,
                }
            )
        self._pyramids: OrderedDict[str, list[np.ndarray]] = OrderedDict()
        self._depths: dict[str, tuple[np.ndarray, float]] = {}
        self._depth_errors: dict[str, float] = {}

    # -- cached inputs ---------------------------------------------------------------------------
    def pyramid(self, name: str) -> list[np.ndarray]:
        """RGB uint8 levels of a source image: full resolution, then halved until 256 px."""
        if name in self._pyramids:
            self._pyramids.move_to_end(name)
            return self._pyramids[name]
        bgr = cv2.imread(str(self.image_dir / name), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(f"source image {self.image_dir / name} is missing or unreadable")
        levels = [cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)]
        while min(levels[-1].shape[:2]) > 256:
            levels.append(cv2.pyrDown(levels[-1]))
        self._pyramids[name] = levels
        size = lambda: sum(lv.nbytes for ls in self._pyramids.values() for lv in ls)  # noqa: E731
        while len(self._pyramids) > 1 and size() > float(self.conf["cache_mb"]) * 1e6:
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

    def depth_at(self, src: dict, uv: np.ndarray, depth_fn: DepthFn) -> np.ndarray:
        """The source's depth map at its pixels uv (N, 2) (COLMAP convention, full resolution)."""
        dmap, s = self.depth(src, depth_fn)
        du = np.clip((uv[:, 0] * s).astype(int), 0, dmap.shape[1] - 1)
        dv = np.clip((uv[:, 1] * s).astype(int), 0, dmap.shape[0] - 1)
        return dmap[dv, du]

    def depth_error(self, src: dict, depth_fn: DepthFn) -> float:
        """The median relative error of the source's depth map at its sparse points (inf with fewer than
        10 of them)."""
        if src["name"] not in self._depth_errors:
            img = self._rec.images[src["image_id"]]
            P = [self._rec.points3D[p.point3D_id].xyz for p in img.points2D if p.has_point3D()]
            _, uv, z = self.inside(src, np.array(P, float).reshape(-1, 3))
            d = self.depth_at(src, uv, depth_fn)
            ok = d > 0
            self._depth_errors[src["name"]] = (
                float(np.median(np.abs(d[ok] - z[ok]) / z[ok])) if ok.sum() >= 10 else float("inf")
            )
        return self._depth_errors[src["name"]]

    @staticmethod
    def inside(src: dict, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indices of the points X (N, 3) in front of the source and inside its image, their pixels in
        COLMAP convention, their z-depths)."""
        sp: Pose = src["pose"]
        cam = src["camera"]
        Xc = X @ sp.R.T.astype(X.dtype) + sp.t.astype(X.dtype)
        z = Xc[:, 2]
        if src["pinhole"] is not None:  # no distortion: K alone (pycolmap's projection is slower)
            fx, fy, cx, cy = src["pinhole"]
            with np.errstate(divide="ignore", invalid="ignore"):  # z <= 0 is masked out below
                u = fx * Xc[:, 0] / z + cx
                v = fy * Xc[:, 1] / z + cy
            # NaN fails every comparison: the bounds also drop non-finite pixels
            ok = (z > 1e-3) & (u >= 0) & (u < cam.width - 1) & (v >= 0) & (v < cam.height - 1)
            idx = np.flatnonzero(ok)
            return idx, np.stack([u[idx], v[idx]], 1), z[idx]
        idx = np.nonzero(z > 1e-3)[0]
        if len(idx) == 0:
            return idx, np.zeros((0, 2)), np.zeros(0)
        uv = cam.img_from_cam(Xc[idx])
        ok = np.all(np.isfinite(uv), axis=1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height - 1)
        return idx[ok], uv[ok], z[idx[ok]]

    @staticmethod
    def _consistent(
        first: np.ndarray, second: np.ndarray, vi: np.ndarray, ui: np.ndarray, shape: tuple, limit: float
    ) -> np.ndarray:
        """Which points (N,) the two best sources see alike: the mean absolute difference of their
        colours (N, 3; NaN where no second source sees the point) over a 7x7 window below `limit` grey
        levels (windows with no second source fail)."""
        diff = np.zeros(shape, np.float32)
        valid = np.zeros(shape, np.float32)
        d = np.abs(first - second).mean(axis=1)
        ok = np.isfinite(d)
        diff[vi[ok], ui[ok]] = d[ok]
        valid[vi[ok], ui[ok]] = 1.0
        num = cv2.boxFilter(diff, -1, (7, 7), normalize=False)
        den = cv2.boxFilter(valid, -1, (7, 7), normalize=False)
        mean = np.where(den > 0, num / np.maximum(den, 1.0), np.inf)
        return ok & (mean[vi, ui] <= limit)

    def seen_through(self, X: np.ndarray, depth_fn: DepthFn, min_sources: int = 2) -> np.ndarray:
        """Which points X (N, 3) lie in space the sources see through: at least `min_sources` of them
        see a surface clearly behind the point, more than see a surface at it. Clearly: beyond the
        depth map's own error (free_space_sigmas x its median relative error at the source's sparse
        points; visibility_rel where it has too few to measure). A 3DGS trained from the air grows such
        floaters near the low views; trees, cars and roofs are where the sources see them."""
        c = self.conf
        through = np.zeros(len(X), np.int32)
        at = np.zeros(len(X), np.int32)
        for src in self.sources:
            idx, uv, z = self.inside(src, X)
            if len(idx) == 0:
                continue
            err = self.depth_error(src, depth_fn)
            ds = self.depth_at(src, uv, depth_fn)
            rel = (
                max(float(c["free_space_sigmas"]) * err, float(c["free_space_min_rel"]))
                if np.isfinite(err)
                else float(c["visibility_rel"])
            )
            tol = ds * rel + float(c["free_space_abs_m"])
            through[idx] += (ds > 0) & (z < ds - tol)
            at[idx] += (ds > 0) & (np.abs(z - ds) <= tol)
        return (through >= min_sources) & (through > at)

    # -- colour ----------------------------------------------------------------------------------
    def score(
        self,
        src: dict,
        X: np.ndarray,
        ray_v: np.ndarray,
        depth_fn: DepthFn | None,
        normal: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The points X (N, 3) the source sees (in its image, within max_angle_deg of the view's rays
        ray_v (N, 3), or with a `normal` (N, 3; NaN: unknown, see surface_normals) within
        max_incidence_deg of it; not hidden in its 3DGS depth unless depth_fn is None): (indices, pixels,
        penalties, metres per pixel)."""
        c = self.conf
        if src["pinhole"] is not None and X.dtype == np.float32:  # the compiled pass (the colour's points)
            return self._score_compiled(src, X, ray_v, depth_fn, normal)
        idx, uv, z = self.inside(src, X)
        if len(idx) == 0:
            return idx, uv, z, z
        ray_s = X[idx] - src["pose"].center.astype(X.dtype)
        norm_s = np.sqrt(np.einsum("ij,ij->i", ray_s, ray_s))
        cosang = np.einsum("ij,ij->i", ray_s, ray_v[idx]) / norm_s
        ok = cosang >= np.cos(np.radians(float(c["max_angle_deg"])))
        if normal is not None and c["max_incidence_deg"]:
            # the normal faces the view: a source that sees the surface from its side has -ray_s . n > 0
            cos_inc = -np.einsum("ij,ij->i", ray_s, normal[idx]) / norm_s
            ok |= cos_inc >= np.cos(np.radians(float(c["max_incidence_deg"])))  # NaN: False
        if depth_fn is not None:
            ds = self.depth_at(src, uv, depth_fn)
            ok &= (ds > 0) & (z <= ds * (1.0 + float(c["visibility_rel"])) + float(c["visibility_abs_m"]))
        idx, uv, z, cosang = idx[ok], uv[ok], z[ok], cosang[ok]
        gsd = z / float(src["camera"].mean_focal_length())
        angle = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
        penalty = angle + float(c["resolution_weight_deg"]) * np.log2(np.maximum(gsd, 1e-6))
        return idx, uv, penalty, gsd

    def _score_compiled(
        self, src: dict, X: np.ndarray, ray_v: np.ndarray, depth_fn: DepthFn | None, normal: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`score` of a pinhole source over float32 points in one compiled pass (source_kernels)."""
        from services.views.source_kernels import score_pinhole

        c = self.conf
        sp: Pose = src["pose"]
        dmap, s = self.depth(src, depth_fn) if depth_fn is not None else (np.zeros((0, 0), np.float32), 1.0)
        use_normal = normal is not None and bool(c["max_incidence_deg"])
        limits = np.array(
            [
                np.cos(np.radians(float(c["max_angle_deg"]))),
                np.cos(np.radians(float(c["max_incidence_deg"]))) if use_normal else -3.0,
                float(c["visibility_rel"]),
                float(c["visibility_abs_m"]),
                float(src["camera"].mean_focal_length()),
                float(c["resolution_weight_deg"]),
            ]
        )
        f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
        return score_pinhole(
            f32(X), f32(ray_v), f32(normal) if use_normal else np.zeros((0, 3), np.float32),
            f32(sp.R), f32(sp.t), f32(sp.center), np.asarray(src["pinhole"], np.float64),
            np.array([src["camera"].width, src["camera"].height], np.float64), f32(dmap), float(s), limits,
        )  # fmt: skip

    def best_sources(self, X: np.ndarray, ray_v: np.ndarray, depth_fn: DepthFn | None, k: int) -> list[int]:
        """Indices of at most k sources, those that are the best or second best (lowest penalty of
        `score`) for the most of the points X (N, 3) seen along the unit rays ray_v (N, 3)."""
        probe = [(si, *self.score(src, X, ray_v, depth_fn)[::2]) for si, src in enumerate(self.sources)]
        picks = np.concatenate(_two_best(len(X), probe))
        counts = np.bincount(picks[picks >= 0], minlength=len(self.sources))
        order = np.argsort(-counts, kind="stable")[:k]
        return [int(i) for i in order if counts[i] > 0]

    def colour(
        self,
        camera: Camera,
        pose: Pose,
        depth: np.ndarray,
        fallback: np.ndarray,
        depth_fn: DepthFn,
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """RGB uint8 (H, W, 3) of the view: each pixel with depth > 0 from its best visible source,
        the others (and those no source sees) from `fallback` (uint8 (H, W, 3)). Returns the image, the
        depth it used and figures (fraction of pixels coloured from sources, sources used)."""
        H, W = depth.shape
        if not (depth > 0).any():
            return fallback, depth, {"source_fraction": 0.0, "sources_used": 0}
        vi, ui = np.nonzero(depth > 0)
        normal = None
        if self.conf["max_incidence_deg"]:  # the normals need every pixel's point: unprojected once
            grid = pixel_points(camera, pose, depth)
            normal = surface_normals(camera, pose, depth, float(self.conf["normal_tolerance"]), grid)[vi, ui]
            X = grid[vi, ui].astype(np.float32)
        else:
            uv_v = np.stack([ui + 0.5, vi + 0.5], 1).astype(np.float64)  # pixel centres, COLMAP convention
            X = pose.unproject(camera.K, uv_v, depth[vi, ui].astype(float)).astype(np.float32)
        ray_v = X - pose.center.astype(np.float32)
        ray_v /= np.linalg.norm(ray_v, axis=1, keepdims=True)
        gsd_v = depth[vi, ui] / camera.K[0, 0]  # metres per view pixel (at the point, along the axis)
        n = len(X)
        # the candidates: sources that are the best or second best for some of a sparse sample of the points
        step = max(1, n // 4000)
        probe = [
            (
                si,
                *self.score(
                    src, X[::step], ray_v[::step], depth_fn, None if normal is None else normal[::step]
                )[::2],
            )
            for si, src in enumerate(self.sources)
        ]
        chosen = sorted({int(i) for i in np.concatenate(_two_best(len(X[::step]), probe)) if i >= 0})
        scored = {si: self.score(self.sources[si], X, ray_v, depth_fn, normal) for si in chosen}
        best_i, second_i = _two_best(n, [(si, idx, pen) for si, (idx, _, pen, _) in scored.items()])
        scored = {si: (idx, uv, gsd / gsd_v[idx]) for si, (idx, uv, _, gsd) in scored.items()}
        first_rgb = np.zeros((n, 3), np.float32)
        second_rgb = np.full((n, 3), np.nan, np.float32)
        used = 0
        for si, (idx, uv, ratio) in scored.items():
            take, take2 = best_i[idx] == si, second_i[idx] == si
            if not (take.any() or take2.any()):
                continue
            used += int(take.any())
            keep = take | take2
            idx, uv, ratio, take = idx[keep], uv[keep], ratio[keep], take[keep]
            levels = self.pyramid(self.sources[si]["name"])
            # source pixels per view pixel: 1/ratio; sample the level where that is about 1
            lvl = int(np.clip(np.floor(np.log2(max(np.median(1.0 / ratio), 1.0))), 0, len(levels) - 1))
            scale = 1.0 / (2**lvl)  # COLMAP pixel coordinates -> OpenCV's at that level
            val = _sample(levels[lvl], uv[:, 0] * scale - 0.5, uv[:, 1] * scale - 0.5).astype(np.float32)
            first_rgb[idx[take]] = val[take]
            second_rgb[idx[~take]] = val[~take]
        has = best_i >= 0
        limit = self.conf["consistency"]
        if limit is not None:  # the two best sources must agree where the point is: else the depth is off
            has &= self._consistent(first_rgb, second_rgb, vi, ui, (H, W), float(limit))
        out = fallback.copy()
        out[vi[has], ui[has]] = np.clip(np.rint(first_rgb[has]), 0, 255).astype(np.uint8)
        return out, depth, {"source_fraction": float(has.sum() / (H * W)), "sources_used": used}
