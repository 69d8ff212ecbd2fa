"""The reducer (section 3.2.3): aerial-ground matches transferred through the rendered views, merged,
made one-to-one and verified in 3D.

Each view's inlier matches (matches/VIEW.h5 of services.matching.views) are observations of the aerial
and ground images: (image keypoint, render keypoint, score, view). Every view's pose is known, and so
is every aerial pose (the aerial model), so:

1. aerial points: a render keypoint matched to aerial images is triangulated from the render's ray and
   the aerial rays; aerial observations farther than `aerial_px` from the point's projection are
   dropped, the point must reproject onto the render keypoint (`render_px`), see it under a real angle
   and agree loosely with the rendered depth (the depth of a CPU-trained 3DGS is too rough to place
   points itself, its rays are not);
2. links: a ground observation (a render keypoint matched to a ground image) is linked to the aerial
   points that project within `link.px` of that render keypoint and are not hidden there (rendered
   depth): the paper's transfer is the case of the same render keypoint matched on both sides; with
   `link.mode` "3d" any view's point serves, so that a view low enough to match the ground image and
   another one high enough to match the aerial images meet at their common 3D points. Each link is an
   aerial-ground match and, through the point, a 2D-3D correspondence of the ground image;
3. merge per aerial-ground pair over all views: duplicates keep one, and the pair's matches are made
   one-to-one, conflicts resolved by score, then by view name, then by keypoint index (deterministic
   whatever the order of the views);
4. PnP per ground image (pycolmap LO-RANSAC + refinement) on its 2D-3D correspondences (with
   `pnp.depth_points` also every render-ground match lifted by the rendered depth); the pose must agree
   with the ground POS (position and attitude within `prior_sigmas` standard deviations, or the
   absolute floors). Matches whose point reprojects within `keep_px` of the ground keypoint are kept;
   ground images whose pose fails get no verified matches (`unverified`);
5. a fundamental-matrix RANSAC per pair on what is left (pairs with >= 8 matches).

Without aerial poses (or with `pnp.enabled` False) the reducer is the paper's plain transfer on the
keypoint tables: render keypoints with an inlier match on both sides.

Outputs (out_dir): matches.h5 (common match file; aerial-ground pairs, aerial first; `matches` are the
merged putative links, `inliers` those passing every check, `views` the view each came through: the
view of its ground observation), database.db (COLMAP database: aerial and ground keypoints, the verified
matches and two-view geometries), ground_poses.json (the PnP pose of each ground image, in the model
frame and in WGS84: a product on its own) and report.json.

Modules: `observations` (step 1), `points` (aerial points and links), `merge` (merge, pairwise check),
`localize` (PnP with the POS gate: `PoseEstimate`), `reducer` (`reduce_views`, `main`), `direct` (the
same check on direct matches, for the baselines), `confs`.
"""

from services.reduce.confs import default_conf
from services.reduce.direct import lift_aerial_keypoints, localize_direct
from services.reduce.localize import (
    PoseEstimate,
    estimate_ground_pose,
    ground_priors,
    prior_agreement,
    prior_chi2,
    trusted_depth_views,
)
from services.reduce.merge import merge_one_to_one
from services.reduce.observations import ViewData, image_set, load_views
from services.reduce.points import aerial_points, link_points
from services.reduce.reducer import main, pose_document, reduce_views, write_match_file

confs = {"default": default_conf}

__all__ = [
    "PoseEstimate",
    "ViewData",
    "aerial_points",
    "confs",
    "default_conf",
    "estimate_ground_pose",
    "ground_priors",
    "image_set",
    "lift_aerial_keypoints",
    "link_points",
    "load_views",
    "localize_direct",
    "main",
    "merge_one_to_one",
    "pose_document",
    "prior_agreement",
    "prior_chi2",
    "reduce_views",
    "trusted_depth_views",
    "write_match_file",
]
