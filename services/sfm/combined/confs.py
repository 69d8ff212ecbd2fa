"""The combined SfM's conf (services.sfm.combined)."""

from __future__ import annotations

from typing import Any

from services.sfm.combined.ambiguity import default_conf as ambiguity_conf
from services.sfm.combined.consistency import default_conf as consistency_conf
from services.sfm.combined.depths import default_conf as depths_conf
from services.sfm.combined.surface import default_conf as surface_conf

default_conf: dict[str, Any] = {
    "ground_pairs": {
        # each ground image with its nearest ground images (POS; 4 left small-walk one image fewer and its
        # ground images 2-3x farther off: docs/measurements.md) ...
        "num_neighbors": 6,
        "max_distance_m": 40.0,  # ... within this distance ...
        "max_heading_deg": 100.0,  # ... whose viewing directions differ by less than this
        "min_inliers": 15,
        # verification: an essential matrix (both cameras calibrated) whose relative pose agrees with
        # the POS: rotation within prior_sigmas x the attitude noise (at least min_rotation_deg), the
        # baseline's direction within the angle the position noise allows (unchecked when the noise
        # is as large as the baseline)
        "ransac_px": 3.0,
        "prior_sigmas": 3.0,
        "min_rotation_deg": 10.0,
        "min_direction_deg": 15.0,
        # ... and, where both images have an attitude tied to the aerial images (the reducer's attitude_tied
        # PnP poses, their std at least tied_attitude_min_std_deg), a relative rotation within prior_sigmas
        # x their stds of those attitudes (at least min_tied_rotation_deg): on the demo's isprs two pairs of
        # repeated facades (8 of 57 and 7 of 55 matches correct) passed the POS 5.8-8.0 degrees off them and
        # one pulled an image a metre off; the true pairs judged there and on isprs-walk stood 0.6-2.3
        # degrees off, and a tied attitude can be 2 degrees off the truth: the floor halfway between
        "tied_attitude_min_std_deg": 0.5,
        "min_tied_rotation_deg": 4.0,
        # ... and of the calibrated camera: a pair whose matches an uncalibrated fundamental matrix explains
        # better than an essential matrix (COLMAP's UNCALIBRATED two-view configuration) is refused; on
        # isprs 3 of the 5 verified pairs without a correct match, none of the true ones
        "require_calibrated": True,
        "min_e_f_inlier_ratio": 0.95,  # ... below this share of F's inliers for E's (COLMAP's default)
        "seed": 0,
        # ... and, when enabled, whose matches fit the scene: lifted onto the aerial surface from the first
        # image's aerial-tied pose, they must place the second camera by PnP where its POS says
        # (services.sfm.combined.surface). Off: the plane proxy is wrong on a third of what a ground camera
        # sees, so true neighbours failed it (isprs-walk: 6 true pairs of 30-56% overlap refused, G0006 cut
        # from its chain); the calibrated-camera and consistency checks refuse the false pairs it caught
        # (docs/measurements.md "The surface check off")
        "surface": {**surface_conf, "enabled": False},
        # ... and whose baseline agrees with where the other pairs and the POS put its images (a
        # translation averaging; services.sfm.combined.consistency)
        "consistency": dict(consistency_conf),
        # ... and whose matches put the scene where the other pairs of the same images put it (a repeated
        # facade matched one window along the street fits the true relative pose): the baselines' lengths
        # their depths give (services.sfm.combined.depths), fitted by the consistency's solution too
        "depths": dict(depths_conf),
    },
    "seed_points": True,  # 3D points of the transferred tracks in the input model
    # ground images with an accepted PnP pose start registered, held at that pose ... (off: the mapper
    # registers them like the others and they are judged like the others; those it leaves out or drops
    # are added at their PnP pose, see add_pnp_images. A PnP pose on points triangulated through a
    # CPU-trained 3DGS's blurry renders can be 0.8 m off within its 0.25 m std, and held fixed it drags
    # the chain of ground images the mapper registers from it: small-walk, README). "trusted": only the
    # poses that rest on rendered depth the reducer trusted (at least seed_min_trusted_ratio of their
    # inliers lifted by the depth of views whose depth agrees with the aerial points: exact renders)
    "seed_pnp_poses": "trusted",
    "seed_min_trusted_ratio": 0.5,
    "min_seed_matches": 15,  # ... when one of their pairs has this many matches (and min_num_matches)
    # ground images with an accepted PnP pose that the mapper could not keep (their 2D-3D support comes
    # from many aerial images, or from the rendered depth, with no pair of min_num_matches) are added
    # to the combined model at that pose, observing the model's points their transferred matches reach
    "add_pnp_images": True,
    "add_max_px": 4.0,  # such an observation must reproject within this (ground pixels)
    "add_min_angle_deg": 2.0,  # a new aerial-ground point must be seen under this angle at least
    # ground images the mapper registered itself (not at an accepted PnP pose) are dropped when the
    # model leaves their camera centre this uncertain (standard deviation along the worst direction from
    # the bundle adjustment's covariance, pixel noise at least 1 px: services.pose_uncertainty.
    # joint_position_stds; None: kept), or when their pose disagrees with their POS (the reducer's limits)
    "max_position_std_m": 0.5,
    # ... or when their verified matches fit two poses alike: the best pose's inliers, and among the rest
    # a second pose with at least min_ratio of them, min_separation_m away (services.sfm.combined.ambiguity:
    # half of a pair's matches a repeated facade shifted by a window)
    "ambiguity": dict(ambiguity_conf),
    "pos_limits": None,  # those POS limits: the reducer's conf["pnp"] (None: services.reduce's defaults)
    "mapping": {
        "min_num_matches": 15,  # pairs with fewer matches are ignored by the mapper
        "abs_pose_min_num_inliers": 15,
        "abs_pose_min_inlier_ratio": 0.15,
        "abs_pose_max_error": 8.0,
        "min_model_size": 3,
        "refine_intrinsics": False,
        "fix_aerial": True,  # the input model (aerial + PnP-seeded ground) stays fixed; BA refines the rest
        # triangulate points seen in two images only: a ground image's match with one neighbour is such a
        # point, and COLMAP 4 leaves them out by default (ignore_two_view_tracks), so a chain of ground
        # images never got an initial pair's points and its neighbours none of its matches as ties
        "two_view_tracks": True,
        "seed": 0,
    },
    # the last adjustment (services.sfm.combined.refine): the ground images sharing min_shared_observations
    # points with other ground images refined with the aerial images held (the seeds too: a PnP pose held
    # fixed places the points the mapper registers its neighbours on; a lone image stays at its pose);
    # observations off by max_reproj_px dropped between rounds
    "refine_ground": {
        "enabled": True,
        "loss": "cauchy",  # pycolmap's LossFunctionType: trivial, soft_l1, cauchy
        "loss_scale_px": 2.0,  # the robust loss's scale (reprojection error in pixels)
        "rounds": 2,  # adjust, then drop observations off by max_reproj_px, and again
        "max_reproj_px": 4.0,
        "min_tri_angle_deg": 1.5,
        "min_shared_observations": 15,
        "max_iterations": 100,
    },
    # chains of ground images the mapper left out, each reconstructed on its own and placed by a
    # similarity on its ties to the aerial points (services.sfm.combined.blocks)
    "blocks": {
        "enabled": True,
        "min_images": 3,  # a chain of fewer unregistered ground images is left to the single-image paths
        "tie_max_m": 0.5,  # a tie agrees with the similarity within this (model metres)
        "min_ties": 20,  # agreeing ties of a placed block ...
        # ... through at least this many of its images: one image's matches alone can all be a repeated
        # facade shifted by a window (services.reduce's pnp.min_other_view_inliers, for one image)
        "min_tie_images": 2,
        "seed": 0,
    },
    "georef": True,
    # GeoPackage/GeoJSON cameras, omega/phi/kappa text and LAS points in out_dir/gis (services.sfm.gis)
    "gis": True,
    "colmap_log_level": 1,
}
