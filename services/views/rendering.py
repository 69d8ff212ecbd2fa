"""Rendering the planned intermediate views: colour PNG, z-depth and the view's camera and pose.

    from services.views import rendering
    r = rendering.SplatRenderer("job/splat")                # the product path: the 3DGS model
    rendering.main(rendering.confs["default"], "plan/views.json", "job/views", r)

Outputs under the output folder: NAME.png (RGB), NAME.depth.npy (float32 z-depth in metres along the
optical axis, 0 where nothing reliable was rendered) and views.json (the plan, each view with its
`image` and `depth` files relative to the folder, and render statistics).

Renderers follow the `Renderer` protocol: `render(camera, pose) -> (rgb uint8 (H, W, 3), depth
float32 (H, W))`. `SplatRenderer` renders the 3DGS model of services.splat; `SourceRenderer` (the
default, conf colour "source") colours its views from the full-resolution aerial images through a
piecewise-planar proxy of the aerial model. `GroundTruthRenderer`
ray-casts the true synthetic scene (services.synth) in the aerial model's frame: it is for tests and
for measuring the upper bound of the method, never the product path.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from services.colmap_model import Camera, Pose
from services.synth import GroundTruthRenderer
from services.views import orthophoto
from services.views.proxy import PlaneProxy
from services.views.proxy import confs as proxy_confs
from services.views.source_colour import SourceImages
from services.views.source_colour import confs as source_confs
from services.views.stereo import StereoSurface
from services.views.stereo import confs as stereo_confs
from services.views.sweep import PlaneSweep
from services.views.sweep import confs as sweep_confs
from services.views.tracks import confs as tracks_confs
from shared.logging import stage

logger = logging.getLogger("midview.views")


confs: dict[str, dict[str, Any]] = {
    "default": {
        "min_alpha": 0.5,  # 3DGS: pixels less opaque than this get no depth
        "max_depth_m": 2000.0,
        # the views' colour: "source" (the full-resolution aerial images through the plane proxy's depth,
        # services.views.source_colour; 2.32x the GT-correct matches of the 3DGS's own on isprs) or
        # "splat" (the 3DGS's own colour and depth)
        "colour": "source",
        "proxy": dict(proxy_confs["default"]),  # services.views.proxy
        "source": dict(source_confs["default"]),  # services.views.source_colour
        # the views' depth: "proxy" (the planes of the sparse model, the 3DGS's surfaces the aerial
        # images do not see through) or "stereo" (the TSDF of the aerial images' pairwise dense stereo,
        # services.views.stereo; the proxy's where it has no surface); bench only: "truth" (a synthetic
        # scene's true depth, the renderer's `scene`: the bound of colour from the aerial images); "sweep"
        # (the proxy's depth refined by a plane sweep over the aerial images, services.views.sweep; on
        # isprs's planned views 0.91% median error against the proxy's 0.75%: off)
        "depth": "proxy",
        # the planner's depth probes: "same" (the views' depth) or another of the above; bench only, to
        # tell what the plan owes to the depth from what the colour owes to it (bench/method.py --render-set)
        "plan_depth": "same",
        "stereo": dict(stereo_confs["default"]),
        "tracks": dict(tracks_confs["default"]),  # the proxy's dense points "tracks"
        "sweep": dict(sweep_confs["default"]),
        "orthophoto": dict(orthophoto.confs["default"]),  # services.views.orthophoto, with the views
    },
}


Progress = Callable[[float, str], None]


class Renderer(Protocol):
    """Renders any pinhole camera of the aerial model's frame."""

    name: str

    def render(self, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """-> (rgb uint8 (H, W, 3), z-depth float32 (H, W), 0 where nothing was hit)."""
        ...


class SplatRenderer:
    """The 3DGS model of services.splat (a training folder, checkpoint or .ply)."""

    name = "splat"

    def __init__(self, model_path: str | Path, backend: str = "auto", min_alpha: float = 0.5):
        from services.splat import load_model

        self.model_path = Path(model_path)
        self.model = load_model(self.model_path)
        self.backend = backend
        self.min_alpha = float(min_alpha)

    def render(self, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        from services import splat

        out = splat.render(self.model, camera, pose, backend=self.backend)
        rgb = np.clip(np.rint(out["color"] * 255.0), 0, 255).astype(np.uint8)
        depth = np.where(out["alpha"] >= self.min_alpha, out["depth"], 0.0).astype(np.float32)
        return rgb, depth


class SourceRenderer:
    """A 3DGS renderer's views coloured from the full-resolution aerial images (services.views.
    source_colour) through the plane proxy's depth (services.views.proxy) where it has one, else the
    3DGS's (without what the aerial images see through: floaters); the 3DGS's colour where no source
    sees a pixel. With colour False, only that depth (the planner's depth probe) and the 3DGS's colour."""

    name = "splat+source"

    def __init__(
        self,
        base: SplatRenderer,
        sparse_dir: str | Path,
        image_dir: str | Path,
        conf: dict | None = None,
        colour: bool = True,
        cache_dir: str | Path | None = None,
        scene: str | Path | None = None,
    ):
        """`cache_dir`: a folder where what is built from the aerial model alone (the stereo surface, the
        learned tracks) is kept for reuse; `scene`: the synthetic scene folder whose true depth conf depth
        "truth" takes."""
        import pycolmap

        from services.views import tracks

        c = {**confs["default"], **(conf or {})}
        rec = pycolmap.Reconstruction(str(sparse_dir))  # read once for the planes and the sources
        self.base = base

        def stereo() -> StereoSurface:
            if cache_dir is not None:
                return StereoSurface.cached(sparse_dir, image_dir, c["stereo"], cache_dir)
            return StereoSurface.build(rec, image_dir, c["stereo"])

        self.stereo = self.truth = None
        if c["depth"] == "stereo":
            self.stereo = stereo()
        dense = None
        if c["proxy"].get("dense_points") == "stereo":
            tilt = float(c["proxy"]["dense_max_tilt_deg"])
            dense = (self.stereo or stereo()).points(
                float(c["proxy"]["dense_voxel_m"]), tilt if tilt >= 0 else None
            )
        elif c["proxy"].get("dense_points") == "tracks":
            dense = tracks.cached(sparse_dir, image_dir, c["tracks"], cache_dir)
        elif c["proxy"].get("dense_points", "none") != "none":
            kind = c["proxy"]["dense_points"]
            raise ValueError(f"unknown dense points {kind!r} of the proxy (none, stereo, tracks)")
        self.proxy = PlaneProxy.from_model(rec, c["proxy"], dense)
        self.sources = SourceImages(rec, image_dir, c["source"])
        if c["depth"] == "truth":
            if scene is None:
                raise ValueError("the views' depth 'truth' needs a synthetic scene (settings.scene)")
            self.truth = GroundTruthRenderer(scene, sparse_dir)
        elif c["depth"] not in ("proxy", "sweep", "stereo"):
            raise ValueError(f"unknown views' depth {c['depth']!r} (proxy, sweep, stereo, truth)")
        self.sweep = PlaneSweep(self.sources, c["sweep"]) if c["depth"] == "sweep" else None
        self.colour = colour
        self.last_stats: dict = {}

    def _depth(self, camera: Camera, pose: Pose) -> np.ndarray:
        """The depth the sources' visibility is tested against: the true depth, the stereo surface's, else
        the 3DGS's."""
        if self.truth is not None:
            return self.truth.render(camera, pose)[1]
        depth = self.base.render(camera, pose)[1]
        if self.stereo is None:
            return depth
        return _nearest(self.stereo.depth(camera, pose), depth)

    def render(self, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth = self.base.render(camera, pose)
        depth_fn = self._depth
        if self.truth is not None:
            depth = depth_fn(camera, pose)
        else:
            depth = self.proxy.fuse(camera, pose, depth, lambda X: self.sources.seen_through(X, depth_fn))
        if self.stereo is not None:
            depth = _nearest(self.stereo.depth(camera, pose), depth)
        if not self.colour:  # a depth probe of the planner: the sweep is for the rendered views
            return rgb, depth
        swept: dict = {}
        if self.sweep is not None:
            depth, swept = self.sweep.refine(camera, pose, depth, depth_fn)
        rgb, depth, self.last_stats = self.sources.colour(camera, pose, depth, rgb, depth_fn)
        self.last_stats.update(swept)
        return rgb, depth


def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The nearer of two depth maps (H, W) where both have a surface, else the one that has (0: none)."""
    both = (a > 0) & (b > 0)
    return np.where(both, np.minimum(a, b), np.maximum(a, b)).astype(np.float32)


class BlockRenderer(SplatRenderer):
    """The whole-scene 3DGS merged with the blocks trained on it (services.splat.blocks.merge_blocks)."""

    name = "splat-blocks"

    def __init__(self, model_path: str | Path, blocks_dir: str | Path, backend: str = "auto", min_alpha=0.5):
        from services.splat import merge_blocks

        super().__init__(model_path, backend, min_alpha)
        self.model, self.merged = merge_blocks(self.model, blocks_dir)


def make_renderer(kind: str, **kwargs: Any) -> Renderer:
    """ "splat" (model_path, backend) or "gt" (scene_dir, model_sparse)."""
    if kind == "splat":
        return SplatRenderer(
            kwargs["model_path"], kwargs.get("backend", "auto"), kwargs.get("min_alpha", 0.5)
        )
    if kind == "gt":
        return GroundTruthRenderer(kwargs["scene_dir"], kwargs.get("model_sparse"))
    raise ValueError(f"unknown renderer {kind!r} (splat, gt)")


def depth_fn(renderer: Renderer) -> Callable[[Camera, Pose], np.ndarray]:
    """The renderer as a depth probe for services.views.planning."""
    return lambda camera, pose: renderer.render(camera, pose)[1]


def image_file(name: str) -> str:
    return f"{name}.png"


def depth_file(name: str) -> str:
    return f"{name}.depth.npy"


def read_render(views_dir: str | Path, view: dict) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8, depth float32) of a rendered view (an entry of views/views.json)."""
    views_dir = Path(views_dir)
    bgr = cv2.imread(str(views_dir / view.get("image", image_file(view["name"]))), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"{views_dir}: render of view {view['name']} missing")
    depth = np.load(views_dir / view.get("depth", depth_file(view["name"])))
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


def main(
    conf: dict,
    views_json: str | Path,
    out_dir: str | Path,
    renderer: Renderer,
    progress: Progress | None = None,
) -> Path:
    """Render every view of `views_json` into out_dir; returns out_dir/views.json. Views whose files
    are already there (from the same pose) are not rendered again."""
    conf = {**confs["default"], **(conf or {})}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = json.loads(Path(views_json).read_text())
    old = {}
    if (out_dir / "views.json").is_file():
        try:
            old = {v["name"]: v for v in json.loads((out_dir / "views.json").read_text())["views"]}
        except (ValueError, KeyError):
            old = {}
    with stage(f"render:{getattr(renderer, 'name', 'renderer')}", logger):
        t0 = time.perf_counter()
        n = len(doc["views"])
        for i, v in enumerate(doc["views"]):
            name = v["name"]
            img, dep = out_dir / image_file(name), out_dir / depth_file(name)
            prev = old.get(name)
            if (
                prev is not None
                and img.is_file()
                and dep.is_file()
                and prev.get("pose") == v["pose"]
                and prev.get("camera") == v["camera"]
                and prev.get("renderer") == getattr(renderer, "name", "")
            ):
                v.update({k: prev[k] for k in ("image", "depth", "render") if k in prev})
                v["renderer"] = prev.get("renderer")
                continue
            t1 = time.perf_counter()
            cam = Camera(**v["camera"])
            pose = Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float))
            rgb, depth = renderer.render(cam, pose)
            depth = np.where(np.isfinite(depth) & (depth > 0) & (depth < conf["max_depth_m"]), depth, 0.0)
            depth = depth.astype(np.float32)
            cv2.imwrite(str(img), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            np.save(dep, depth)
            v["image"], v["depth"] = img.name, dep.name
            v["renderer"] = getattr(renderer, "name", "")
            v["render"] = {
                "seconds": round(time.perf_counter() - t1, 3),
                "valid_depth": float((depth > 0).mean()),
                **getattr(renderer, "last_stats", {}),
            }
            if progress is not None:
                progress((i + 1) / max(n, 1), f"rendered {name}")
        doc["rendered"] = {"renderer": getattr(renderer, "name", ""), "seconds": time.perf_counter() - t0}
        path = out_dir / "views.json"
        path.write_text(json.dumps(doc, indent=1))
        logger.info("%d views rendered in %.1f s -> %s", n, time.perf_counter() - t0, out_dir)
    return path
