"""The view planners' conf (services.views)."""

from __future__ import annotations

from typing import Any

from services.conf import merge_conf

BASE: dict[str, Any] = {
    "planner": "both",  # paper | ground-aware | both (measured best: bench/method.py)
    "views_per_ground_image": 4,
    "target": {
        "ray_cone_deg": 1.5,  # sparse points within this angle of a ray count as on it
        "min_points": 3,
        "quantile": 0.25,  # of the distances of the points on the ray: the first surface, not what's behind
        "depth_window": 5,  # pixels (at the depth probe's size) around the principal point
        "probe_width": 160,  # depth probes are rendered this wide
        # the ground targets' depth probe stands min_target_m ahead of the camera on its principal ray,
        # past the floaters a 3DGS trained on aerial images leaves in front of street-level cameras
        # (bench/targets.py on small-walk: 11 of 30 targets within 15% of the true distance against 8; the
        # same 30 of 40 ground images within 0.5 m and 2% more GT-correct matches: off by default)
        "probe_from_min": False,
        # a ground camera's target: where its optical axis stops being free space in the aerial cameras'
        # depth (a 3DGS trained on them renders their depth well, and the ground camera's own depth probe
        # badly: floaters metres ahead, facades seen through). On small-walk the distance along the axis
        # came within 3 m of the true one for 15 of 29 ground images, 9 by the probe and the points; but
        # on the same 3DGS as without it, GT-correct 1.024x on small-walk, 0.943x on small, registration
        # unchanged on both (docs/measurements.md): off by default
        "carve": {
            "enabled": False,
            "width": 200,  # the aerial depth maps' width (pixels)
            "step_m": 0.25,  # along the ray
            "margin_m": 0.5,  # a camera sees through a point when its depth is this much beyond it
            "free_fraction": 0.25,  # the surface: fewer than this share of the cameras see through
            "min_views": 2,  # aerial cameras that must see a point for it to count
        },
    },
    "paper": {
        "height_fraction": 0.5,  # equation 3: half the height above the target
        "extra_height_fractions": [],  # more views per aerial camera at these fractions (named P-<stem>-hNN)
        "max_width": 1024,  # views keep the aerial camera's field of view at this width
        "views_per_ground_image": None,  # None: the conf's views_per_ground_image
        # which paper views serve a ground image best: "covisible" (with a depth probe: the larger the
        # fraction of what the ground camera sees that the view sees too, at least min_covisible),
        # "covisible-heading" (of those, the most alike in heading and distance) or "target" (the ground
        # camera sees the view's target; the heading and distance between them)
        "relevance": "covisible",
        "min_covisible": 0.05,
        "surface": "points",  # what the ground camera sees (see ground.surface)
    },
    "ground": {
        "look_ahead_m": 15.0,  # target when the optical axis meets nothing in [min_target_m, max_target_m]
        "min_target_m": 4.0,
        "max_target_m": 40.0,
        "camera_height_m": 1.5,  # ground cameras above the terrain
        # the ground cameras' heights from the terrain under them: GNSS heights are the noisiest part of a
        # POS (the synthetic presets': 4 m std, some cameras metres underground or in the air), a camera on
        # a walker or a car stands camera_height_m above the street. The terrain's height: the low quantile
        # of the aerial model's sparse points within terrain_radius_m (a CPU-trained 3DGS's depth seen from
        # above is metres too low there), fused with the POS height by their std (terrain_std_m)
        "height_from_terrain": True,
        "terrain_std_m": 0.5,
        "terrain_radius_m": 10.0,
        "terrain_quantile": 0.1,
        "terrain_min_points": 10,
        # (height above the ground camera in metres, placement), in order of preference: the first
        # `views_per_ground_image` that are not occluded are kept. Placements: "at" (the ground camera
        # itself: what it sees, from where it sees it, coloured from the aerial images through the views'
        # depth; on isprs with views through the true depth 12 of 20 ground images registered, all within
        # 0.5 m, against 11 and 8 without it: docs/measurements.md), "above" (straight above the ground
        # camera), "back" (moved back along its heading by the height: a 45 degree line), "aerial" (on the
        # segment to the aerial camera seeing the target most like the ground camera).
        "placements": [
            [0.0, "at"],
            [10.0, "back"],
            [20.0, "aerial"],
            [5.0, "above"],
            [20.0, "above"],
            [10.0, "above"],
            [5.0, "back"],
            [10.0, "aerial"],
            [30.0, "aerial"],
        ],
        "max_width": 1024,  # views use the ground camera's intrinsics, scaled to at most this width
        "views_per_ground_image": None,  # None: the conf's views_per_ground_image
        "fov_scale": 1.0,  # > 1 widens the field of view (focal length divided by it)
        "occlusion_ratio": 0.85,  # occluded: the view's depth towards the target is below this x its distance
        # keep views that no aerial image is a candidate of: the reducer's "3d" links reach their render
        # keypoints through the aerial points of the other views (services.reduce)
        "keep_without_aerial": True,
        # with a depth probe: a view must see at least this fraction of the surface the ground camera sees
        # from its POS pose (probed `covisibility_width` pixels wide; 0: unchecked; when no placement does,
        # the unoccluded ones are kept, the most covisible first). That surface: "depth",
        # its own depth probe (a CPU-trained 3DGS seen from the street shows floaters near it), or
        # "points", the aerial model's sparse points it sees (nearest per 4 px: mostly the street near it,
        # which views from above do not see: few placements pass 0.5)
        "min_covisible": 0.5,
        "covisibility_width": 96,
        "surface": "depth",
    },
    "candidates": {
        "aerial": 4,  # candidate aerial images per view
        "ground": 2,  # candidate ground images per view
        "margin": 0.05,  # the target may project this fraction of the image size outside it
        "ground_margin": 0.15,  # larger for ground cameras (POS noise of metres)
        "max_angle_deg": 75.0,  # between the view's and the image's viewing directions towards the target
        "max_ground_distance_m": 60.0,
        "nadir_pitch_deg": -80.0,  # aerial images steeper than this are nadir
        "skip_nadir": True,  # for oblique views (nadir images share almost nothing with ground views)
        "cover_aerial": True,  # make every aerial image that can see a ground target a candidate somewhere
    },
    "seed": 0,
}


confs: dict[str, dict[str, Any]] = {
    "paper": merge_conf(BASE, {"planner": "paper"}),
    "ground-aware": merge_conf(BASE, {"planner": "ground-aware"}),
    "both": merge_conf(BASE, {"planner": "both"}),
}
