"""The views' depth refined by a multi-view plane sweep over the aerial images, guided by a prior depth.

The plane proxy (services.views.proxy) and the 3DGS's depth place a view's surfaces within about 5%: the
sparse model holds few points on the lower facades, and a CPU-trained 3DGS bulges and floats. A view
coloured through such a depth shows each aerial image's texture shifted by the error, and the texture
no longer lands where the ground image has it. The aerial images themselves fix the depth: where it is
right, every aerial image that sees the point shows the same texture around it.

For every pixel of the view (at a reduced width) this tries depths along its ray around the prior, the
prior times factors spread evenly in log depth over [1/(1 + range), 1 + range]; every hypothesis is
a surface of the prior's shape at that scale, so a window of pixels follows a slanted street or a facade
the way the prior does (a plane sweep along the prior instead of fronto-parallel planes, Gallup et al.
2007). The aerial images that see the view best (services.views.source_colour) are sampled there at the
pyramid level of the view's pixel size, and each pair of them is compared by normalised cross-correlation
over a window; a hypothesis scores the mean of its best `top_pairs` pairs (an image that does not see the
point, hidden or off its side, pairs badly and drops out). The best hypothesis, refined between its
neighbours by a parabola, replaces the prior where it scores at least `min_ncc`, `min_gain` more than
the prior itself, and does not lie at the range's edge; the correction (a ratio to the prior) is median
filtered and brought back to the view's full resolution, so the prior keeps its outlines.

Measured (docs/measurements.md, bench/views_depth.py): on the analytic scene of tests/test_view_sweep.py
it brings a prior 4% off, blind to 0.3 m recesses, within 0.06% (median); at the planned views of `isprs`
it moves the plane proxy's depth further from the truth (median 0.91% against 0.75%, within 2% of the
truth 63% of the seen pixels against 69%): photo-consistency between aerial images 50 m away picks wrong
depths on repeated facade textures more often than it corrects the proxy. Off by default (render conf
depth "sweep").

    sweep = PlaneSweep(sources)                                 # services.views.source_colour.SourceImages
    depth, stats = sweep.refine(camera, pose, prior, depth_fn)  # z-depth (H, W), 0 = no surface
"""

from __future__ import annotations

import logging
import time
from itertools import combinations
from typing import Any

import cv2
import numpy as np

from services.colmap_model import Camera, Pose
from services.views.source_colour import DepthFn, SourceImages

logger = logging.getLogger("midview.views.sweep")

confs: dict[str, dict[str, Any]] = {
    "default": {
        "width": 320,  # the sweep runs at this width of the view (about the aerial images' pixel size)
        "range": 0.25,  # hypotheses from prior / (1 + range) to prior * (1 + range)
        "hypotheses": 48,  # spread evenly in log depth
        "sources": 5,  # aerial images compared per view (10 pairs)
        "visibility": False,  # choose them only among those that see the prior's points (their 3DGS depth)
        "window": 7,  # pixels (at the sweep's width) of the correlation window
        "top_pairs": 2,  # a hypothesis scores the mean NCC of its best pairs
        "min_ncc": 0.5,  # the best hypothesis must score this much to replace the prior
        "min_gain": 0.1,  # and this much more than the prior itself
        "min_std": 2.0,  # grey levels: flatter windows do not correlate
        "median": 5,  # median filter of the correction (pixels at the sweep's width)
    },
}


def _ncc(a: np.ndarray, b: np.ndarray, valid: np.ndarray, window: int, min_std: float) -> np.ndarray:
    """Windowed normalised cross-correlation of two images (h, w) float32 over the pixels valid in both
    (h, w) float32 0/1; -1 where fewer than half the window is valid or either side is flat."""
    box = lambda x: cv2.boxFilter(x, -1, (window, window), normalize=False)  # noqa: E731
    n = box(valid)
    a, b = a * valid, b * valid
    sa, sb = box(a), box(b)
    nn = np.maximum(n, 1.0)
    va = box(a * a) / nn - (sa / nn) ** 2
    vb = box(b * b) / nn - (sb / nn) ** 2
    cov = box(a * b) / nn - sa * sb / nn**2
    ok = (n >= 0.5 * window * window) & (va > min_std**2) & (vb > min_std**2)
    return np.where(ok, cov / np.sqrt(np.maximum(va * vb, 1e-12)), -1.0).astype(np.float32)


def _parabola_offset(lo: np.ndarray, mid: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The offset (-0.5..0.5 steps) of the maximum of the parabola through three equally spaced scores."""
    den = lo - 2.0 * mid + hi
    off = np.where(den < -1e-6, 0.5 * (lo - hi) / np.where(den < -1e-6, den, -1.0), 0.0)
    return np.clip(off, -0.5, 0.5)


class PlaneSweep:
    """Refines a view's depth against the aerial images of a SourceImages (their poses and pyramids)."""

    def __init__(self, sources: SourceImages, conf: dict | None = None):
        self.sources = sources
        self.conf = {**confs["default"], **(conf or {})}

    def _grid(self, camera: Camera, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K at the sweep's width, the prior depth there (h, w), nearest samples)."""
        H, W = prior.shape
        s = min(1.0, float(self.conf["width"]) / W)
        w, h = max(1, round(W * s)), max(1, round(H * s))
        K = camera.K.copy()
        K[0] *= w / W
        K[1] *= h / H
        return K, cv2.resize(prior, (w, h), interpolation=cv2.INTER_NEAREST)

    def _warp(
        self, si: int, level: np.ndarray, scale: float, X: np.ndarray, pix: tuple, shape: tuple
    ) -> tuple[np.ndarray, np.ndarray]:
        """Grey source image `level` (at `scale` of full resolution) sampled at the points X (N, 3) of the
        view's pixels pix (rows, cols): (image (h, w) float32, valid (h, w) float32)."""
        idx, uv, _ = self.sources.inside(self.sources.sources[si], X)
        mx = np.full(shape, -1e4, np.float32)
        my = np.full(shape, -1e4, np.float32)
        mx[pix[0][idx], pix[1][idx]] = uv[:, 0] * scale - 0.5
        my[pix[0][idx], pix[1][idx]] = uv[:, 1] * scale - 0.5
        img = cv2.remap(level, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        valid = np.zeros(shape, np.float32)
        valid[pix[0][idx], pix[1][idx]] = 1.0
        return img, valid

    def _levels(self, chosen: list[int], X: np.ndarray, px_m: np.ndarray) -> list[tuple[np.ndarray, float]]:
        """Per chosen source, its grey pyramid level whose pixels are about the view's sweep pixels
        (px_m (N,) metres at the points X (N, 3)) and that level's scale."""
        out = []
        for si in chosen:
            src = self.sources.sources[si]
            levels = self.sources.pyramid(src["name"])
            idx, _, z = self.sources.inside(src, X)
            ratio = np.median(px_m[idx] / (z / float(src["camera"].mean_focal_length()))) if len(idx) else 1.0
            lvl = int(np.clip(np.floor(np.log2(max(ratio, 1.0))), 0, len(levels) - 1))
            grey = cv2.cvtColor(levels[lvl], cv2.COLOR_RGB2GRAY).astype(np.float32)
            out.append((grey, 1.0 / 2**lvl))
        return out

    def refine(
        self, camera: Camera, pose: Pose, prior: np.ndarray, depth_fn: DepthFn
    ) -> tuple[np.ndarray, dict]:
        """The view's z-depth (H, W) float32 refined from `prior` (H, W; 0 = no surface, kept 0) and
        figures: the fraction of the prior's pixels refined, the sources compared, seconds.
        `depth_fn` renders a depth at a source camera (the sources' visibility, as for the colour)."""
        c = self.conf
        t0 = time.perf_counter()
        K, small = self._grid(camera, prior)
        rows, cols = np.nonzero(small > 0)
        stats = {"sweep_refined": 0.0, "sweep_sources": 0, "sweep_seconds": 0.0}
        if len(rows) < c["window"] ** 2:
            return prior, stats
        uv = np.stack([cols + 0.5, rows + 0.5], 1).astype(np.float64)
        C = pose.center
        rays = pose.unproject(K, uv, np.ones(len(uv))) - C  # world ray per unit z-depth (N, 3)
        z0 = small[rows, cols].astype(np.float64)
        X0 = C + z0[:, None] * rays
        unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        step = max(1, len(X0) // 4000)
        # by angle and resolution alone: where the prior misses a surface, the sources that see it see it
        # nearer than the prior's point, and a visibility test against their depth would turn them away
        chosen = self.sources.best_sources(
            X0[::step], unit[::step], depth_fn if c["visibility"] else None, int(c["sources"])
        )
        stats["sweep_sources"] = len(chosen)
        if len(chosen) < 2:
            return prior, stats
        levels = self._levels(chosen, X0, z0 / K[0, 0])
        pairs = list(combinations(range(len(chosen)), 2))
        top = min(int(c["top_pairs"]), len(pairs))
        n_hyp = int(c["hypotheses"]) | 1  # odd: the middle one is the prior itself
        factors = np.exp(np.linspace(-np.log1p(c["range"]), np.log1p(c["range"]), n_hyp))
        shape, pix = small.shape, (rows, cols)
        scores = np.full((len(factors), len(rows)), -1.0, np.float32)
        for k, f in enumerate(factors):
            X = C + (z0 * f)[:, None] * rays
            warped = [self._warp(si, g, s, X, pix, shape) for si, (g, s) in zip(chosen, levels, strict=True)]
            ncc = np.stack(
                [
                    _ncc(
                        warped[a][0],
                        warped[b][0],
                        warped[a][1] * warped[b][1],
                        int(c["window"]),
                        c["min_std"],
                    )
                    for a, b in pairs
                ]
            )
            best = -np.sort(-ncc, axis=0)[:top].mean(axis=0)
            scores[k] = best[rows, cols]
        k = np.argmax(scores, axis=0)
        n = np.arange(len(rows))
        inner = (k > 0) & (k < len(factors) - 1)
        accept = inner & (scores[k, n] >= c["min_ncc"]) & (scores[k, n] - scores[n_hyp // 2] >= c["min_gain"])
        kk = np.clip(k, 1, len(factors) - 2)
        off = _parabola_offset(scores[kk - 1, n], scores[kk, n], scores[kk + 1, n])
        log_step = np.log(factors[1] / factors[0]) if len(factors) > 1 else 0.0
        ratio = np.ones(shape, np.float32)
        ratio[rows[accept], cols[accept]] = np.exp(np.log(factors[k[accept]]) + off[accept] * log_step)
        if c["median"] and c["median"] > 1:
            ratio = cv2.medianBlur(ratio, int(c["median"]) | 1)
        H, W = prior.shape
        full = cv2.resize(ratio, (W, H), interpolation=cv2.INTER_LINEAR)
        out = np.where(prior > 0, prior * full, 0.0).astype(np.float32)
        stats["sweep_refined"] = float(accept.mean())
        stats["sweep_seconds"] = round(time.perf_counter() - t0, 3)
        return out, stats
