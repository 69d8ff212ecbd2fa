"""Synthetic aerial + ground survey of procedural urban blocks with exact ground truth.

    from services.synth import confs, main, load_gt, read_depth
    main(confs["small"], Path("/tmp/synth_small"), seed=0)    # render a scene folder (docs/formats.md)
    gt = load_gt("/tmp/synth_small")                           # true cameras, poses, depth, co-visibility

The renderer (kernels.py) ray-casts textured boxes, spheres and the ground plane with numba; it is
independent of any 3DGS code. Numba is only imported when rendering.
"""

from .gt import SCENE_FILES, SceneGT, load_gt, read_covisible, read_depth, scene_complete
from .pipeline import main
from .presets import confs
from .truth_renderer import GroundTruthRenderer, similarity_fit

__all__ = [
    "GroundTruthRenderer",
    "SCENE_FILES",
    "SceneGT",
    "confs",
    "load_gt",
    "main",
    "read_covisible",
    "read_depth",
    "scene_complete",
    "similarity_fit",
]
