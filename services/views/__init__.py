"""Intermediate views between the aerial and the ground cameras: planning them (`views.json`) and
rendering them.

Two planners, in the frame of the aerial model (local ENU, metres, z up; poses are cam_from_world,
docs/formats.md):

- **paper** (section 3.2.2, equations 3-4): for every aerial camera {R_a, C_a}, the ground target T is
  where its principal ray meets the scene. The camera is lowered vertically to `height_fraction` of its
  height above T, C_r = (X_a, Y_a, Z_T + (Z_a - Z_T) / 2), and turned about its own x axis by the angle
  beta between C_a->T and C_r->T so that T is again on its principal ray. In our convention
  (R_world_from_cam = R_a^T, turned about the camera x axis): R_world_from_cam_r = R_a^T @ Rx(theta),
  i.e. cam_from_world R_r = Rx(-theta) @ R_a, with |theta| = beta; theta > 0 tilts the optical axis
  upwards (towards the horizon) for a camera with a level x axis. A nadir camera gives beta = 0: a
  lower nadir view.
- **ground-aware**: for every ground camera (POS: noisy position and attitude), its target T (where its
  optical axis meets the scene, else a point `look_ahead_m` ahead), and views at several heights above
  the ground camera looking at T: straight above the ground camera, moved back along its heading, or on
  the segment from the ground camera to the aerial camera that sees T most like it does. A ground
  camera's POS height (GNSS: metres of noise) is first fused with the terrain under it plus the camera's
  height above the street (`place_ground_on_terrain`).

Targets come from a depth callback (e.g. a rendered depth map of the 3DGS model) when one is given, else
from the aerial model's sparse points near the ray, else from the terrain plane.

Each view gets candidate aerial and ground images for matching, chosen by POS geometry: the target must
project into the image, the viewing directions towards the target must be alike (angle), nadir aerial
images are skipped for oblique views. `views_per_ground_image` views are kept per ground image (for the
paper planner: the paper views most relevant to it), and every aerial image that can see a ground
target is made a candidate of at least one view.

    from services.views import planning
    path = planning.main(planning.confs["ground-aware"], "sfm/sparse", "scene/pos.csv",
                         "scene/cameras.json", "sfm/georef.json", "plan/views.json")

Rendering them (`rendering`): a colour PNG and a z-depth per view from a `Renderer` (the 3DGS, its views
coloured from the full-resolution aerial images through a piecewise-planar proxy of the aerial model
(`proxy`, `source_colour`), or the ground truth of a synthetic scene for tests and upper bounds).

Modules: `confs`, `scene` (what the planners know: the aerial model, the ground POS, and the
scene's queries with the rays and depth probes they read), `specs` (`ViewSpec`, candidates,
views.json), `paper` (equations 3-4 and the paper's planner) and `ground_aware` (the planners),
`planning` (`main` of plan_views), `rendering` (`main` of render_views), `proxy` (the planes of the
aerial model), `source_colour` (colour from the aerial images).
"""

from services.geometry import angle_deg, look_at, optical_axis, pitch_deg
from services.views import orthophoto, planning, rendering
from services.views.confs import confs
from services.views.ground_aware import (
    ground_target,
    ground_view_candidates,
    plan_ground_aware,
    surface_targets,
)
from services.views.paper import paper_viewpoint, plan_paper, select_paper
from services.views.planning import NoViews, plan
from services.views.proxy import PlaneProxy
from services.views.rendering import (
    BlockRenderer,
    GroundTruthRenderer,
    Renderer,
    SourceRenderer,
    SplatRenderer,
    depth_fn,
    make_renderer,
    read_render,
)
from services.views.scene import (
    Scene,
    load_scene,
    place_ground_on_terrain,
    ray_plane,
    ray_target_points,
    scene_terrain_z,
    terrain_height,
)
from services.views.specs import ViewSpec, cover_aerial, read_views, summary, write_views

__all__ = [
    "PlaneProxy",
    "BlockRenderer",
    "GroundTruthRenderer",
    "NoViews",
    "Renderer",
    "Scene",
    "SourceRenderer",
    "SplatRenderer",
    "ViewSpec",
    "angle_deg",
    "confs",
    "cover_aerial",
    "depth_fn",
    "ground_target",
    "ground_view_candidates",
    "load_scene",
    "look_at",
    "make_renderer",
    "optical_axis",
    "orthophoto",
    "paper_viewpoint",
    "pitch_deg",
    "place_ground_on_terrain",
    "plan",
    "plan_ground_aware",
    "plan_paper",
    "planning",
    "ray_plane",
    "ray_target_points",
    "read_render",
    "read_views",
    "rendering",
    "scene_terrain_z",
    "select_paper",
    "summary",
    "surface_targets",
    "terrain_height",
    "write_views",
]
