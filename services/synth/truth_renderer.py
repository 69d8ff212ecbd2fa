"""The ground-truth renderer of a synthetic scene: the true scene ray-cast at any camera of the aerial
model's frame, with the aerial lighting (the views' `Renderer` protocol, services.views.rendering). For
tests and for the upper bound of the method (perfect views), never the product path."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose

logger = logging.getLogger("midview.views")


def similarity_fit(src: np.ndarray, tgt: np.ndarray, scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """tgt ~ s R src + t (least squares)."""
    ms, mt = src.mean(0), tgt.mean(0)
    a, b = src - ms, tgt - mt
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / max((a**2).sum(), 1e-12)) if scale else 1.0
    return s, R, mt - s * R @ ms


class GroundTruthRenderer:
    """Ray-casts the true scene of a synthetic scene folder (services.synth) with the aerial lighting.

    Views are given in the aerial model's frame; `model_sparse` (the aerial SfM model) aligns it to the
    truth with a similarity fitted on the aerial camera centres, so that renders and depths agree with the
    model the way a perfect 3DGS of that model would. Without it, the frames are related through WGS84
    (`frame`: the model's LocalFrame; identity when None).
    """

    name = "gt"

    def __init__(
        self,
        scene_dir: str | Path,
        model_sparse: str | Path | None = None,
        frame: Any = None,
        supersample: int = 1,
    ):
        from services.synth.pipeline import Renderer as SynthRenderer
        from services.synth.pipeline import build_survey, light_array

        self.scene_dir = Path(scene_dir)
        meta = json.loads((self.scene_dir / "gt" / "scene.json").read_text())
        conf, seed = meta["conf"], int(meta["seed"])
        tex = meta.get("textures")
        tex_dir = Path(tex) if tex else None
        if tex_dir is not None and not tex_dir.is_dir():
            raise FileNotFoundError(f"the scene's textures {tex_dir} are missing: cannot re-render it")
        photos, scene, aerial, ground, _ = build_survey(conf, seed, tex_dir)
        self._check_views(aerial + ground)
        self.renderer = SynthRenderer(scene, photos, seed, conf["render"]["grid_cell"])
        self.light = light_array(conf["lighting"]["aerial"])
        self.lighting = conf["lighting"]["aerial"]
        self.seed = seed
        self.ss = int(supersample)
        self.s, self.R, self.t = self._alignment(model_sparse, frame)

    def _check_views(self, views: list) -> None:
        from services.colmap_model import read_model

        _, poses = read_model(self.scene_dir / "gt" / "sparse")
        for v in views[:3]:
            if v.name in poses and np.linalg.norm(poses[v.name].center - v.C) > 1e-3:
                raise RuntimeError(f"{self.scene_dir}: the rebuilt scene does not match gt/sparse ({v.name})")

    def _alignment(self, model_sparse, frame) -> tuple[float, np.ndarray, np.ndarray]:
        """truth_from_model similarity."""
        if model_sparse is not None:
            from services.colmap_model import read_model

            _, est = read_model(model_sparse)
            _, gt = read_model(self.scene_dir / "gt" / "sparse")
            names = sorted(n for n in est if n in gt)
            if len(names) >= 3:
                src = np.array([est[n].center for n in names])
                tgt = np.array([gt[n].center for n in names])
                s, R, t = similarity_fit(src, tgt, scale=True)
                res = np.linalg.norm(s * src @ R.T + t - tgt, axis=1)
                logger.info(
                    "ground-truth renderer: model aligned to the truth on %d cameras (scale %.5f, "
                    "residual median %.3f m)",
                    len(names),
                    s,
                    float(np.median(res)),
                )
                return s, R, t
        if frame is not None:
            from services.pos import LocalFrame

            meta = json.loads((self.scene_dir / "gt" / "scene.json").read_text())
            truth = LocalFrame(**meta["origin"])
            P = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100]], float)
            Q = truth.from_wgs84(*frame.to_wgs84(P))
            s, R, t = similarity_fit(P, Q, scale=False)
            return 1.0, R, t
        return 1.0, np.eye(3), np.zeros(3)

    def render(self, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        from services.synth.cameras import View
        from services.synth.imaging import develop

        if camera.model != "PINHOLE":
            raise ValueError("the ground-truth renderer renders PINHOLE cameras only")
        C = self.s * self.R @ pose.center + self.t
        Rwc = self.R @ pose.R.T
        lin, depth = self.renderer(View("view", "aerial", Rwc, C), camera, self.light, self.ss)
        # sensor noise seeded by the pose: the same view renders to the same bytes whatever the order
        key = np.frombuffer(np.round(np.concatenate([pose.R.ravel(), pose.t]), 6).tobytes(), np.uint32)
        rgb = develop(lin, self.lighting, np.random.default_rng([self.seed, 7, *key[:16].tolist()]))
        return rgb, (depth / self.s).astype(np.float32)
