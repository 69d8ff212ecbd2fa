"""3D Gaussian Splatting of an aerial survey: training, PLY export and rendering of new views.

    from services.splat import confs, main, load_model, render
    out = main(confs["fast"], "scene/gt/sparse", "scene/images", "runs/splat", prefix="aerial/")
    model = load_model(out)
    view = render(model, camera, pose)          # color (H, W, 3), depth (H, W), alpha (H, W)

Backends (`backend.rasterization`): "cpu" (numba tile rasterizer, services/splat/cpu), "cuda" (gsplat)
and "reference" (plain PyTorch, the test oracle); "auto" picks cuda when available.
"""

from services.conf import parse_overrides

from .backend import rasterization, resolve_backend
from .blocks import merge_blocks
from .model import create_splats
from .ply import load_ply, save_ply
from .render import load_model, look_at, lowered_pose, render
from .strategy import DefaultStrategy
from .train import SceneData, Trainer, View, confs, epochs_capped, load_scene, main, rescale_schedule

__all__ = [
    "DefaultStrategy",
    "SceneData",
    "Trainer",
    "View",
    "confs",
    "create_splats",
    "load_model",
    "load_ply",
    "load_scene",
    "merge_blocks",
    "look_at",
    "lowered_pose",
    "main",
    "parse_overrides",
    "rasterization",
    "render",
    "rescale_schedule",
    "epochs_capped",
    "resolve_backend",
    "save_ply",
]
