"""The reducer's conf (services.reduce): every threshold of observations, points, links, PnP and the
pairwise check, in one dict."""

from __future__ import annotations

from typing import Any

from services.reduce.tracks import default_conf as tracks_default_conf

default_conf: dict[str, Any] = {
    "min_score": 0.0,  # render matches below this LightGlue score are not transferred
    "depth_interp": "bilinear",
    "edge_window": 5,  # render keypoints where the depth varies by more than edge_ratio in this window
    "edge_ratio": 1.15,  # (max / min) are dropped: depth edges are where renders are least reliable
    "aerial_px": 4.0,  # aerial observations must lie within this of their point's projection (pixels)
    "triangulation": {
        "render_px": 2.0,  # the point must reproject within this of the render keypoint
        "min_angle_deg": 2.0,  # between the render's ray and an aerial ray
        "depth_rel": 0.3,  # loose agreement with the rendered depth (None: unchecked) ...
        "depth_abs": 1.0,  # ... within depth_rel x depth + depth_abs metres
    },
    # how a ground observation (render keypoint) finds aerial points: "3d" (any view's point projecting
    # within px of it, visible there) or "identity" (only the same render keypoint: the paper)
    "link": {"mode": "3d", "px": 2.0, "visibility_rel": 0.05, "visibility_abs": 0.5},
    "pnp": {
        "enabled": True,
        "ransac_px": 6.0,  # LO-RANSAC threshold (ground pixels)
        "keep_px": 3.0,  # matches within this of the estimated pose are kept (the 3 px of GT-correct)
        # also use render-ground matches lifted by the rendered depth: False, True, or "trusted" (only
        # views whose rendered depth agrees with their triangulated aerial points: median relative
        # difference <= depth_trust; exact renders qualify, a CPU-trained 3DGS hardly does)
        "depth_points": "trusted",
        "depth_trust": 0.01,
        "min_trust_views": 5,  # measured views needed to trust the renderer where a view can't be measured
        "min_spread": 0.05,  # the inliers' bounding box must cover this fraction of the image
        # the camera centre's standard deviation from its inliers (linearized, pixel noise = their RMS
        # residual, >= 1 px) along its worst direction: inliers clustered on a patch of facade fit poses
        # metres apart (a sideways shift trades with a turn), whatever their number (None: unchecked)
        "max_position_std_m": 0.25,
        # ... counting each view's surface as a few percent too near or too far (pose_uncertainty.DepthScale:
        # the points it gave their depth scale together about its centre and move a camera that sees them
        # along the line from that centre). On isprs a ground image placed 6.1 m off through a view 20 m
        # away at another ground camera, all 58 inliers on that view's surface: std 0.17 m without, 0.82 m
        # with 5%; the accepted poses within 0.2 m of the truth 0.03-0.12 m -> 0.04-0.12 m (0 or None: off)
        "depth_scale_std": 0.05,
        "min_inliers": 12,  # inliers of a consensus (verify_on_consensus) ...
        # ... and of an accepted pose: the covariance above sees pixel noise, not 3D points biased by a
        # blurry render; with 12 inliers a fresh demo accepted a pose 2.2 m off at a 0.10 m std (the nine
        # poses accepted with perfect views have 30 or more)
        "min_pose_inliers": 20,
        # inliers through rendered views other than the one holding most, for an accepted pose: one view's
        # matches alone can be a repeated facade shifted by a window period, all agreeing on a wrong camera
        # (isprs-walk: a pose 4.0 m off on 24 inliers of one view, std 0.17 m), and an accepted pose seeds
        # the combined SfM and anchors its ground pairs' surface check; 4 = a P3P sample and one point to
        # check it. Such a consensus still verifies its matches (verify_on_consensus). Direct matches,
        # without views, are not counted
        "min_other_view_inliers": 4,
        "min_inlier_ratio": 0.15,
        # a pose's attitude is tied to the aerial images (its record's attitude_tied) when its inliers are a
        # consensus through two views at least that agrees with the POS and pin its attitude within this
        # (std about the worst axis, degrees): the combined SfM checks ground pairs' relative rotations
        # against such attitudes (None: none is)
        "max_attitude_std_deg": 1.0,
        "prior_sigmas": 3.0,  # the pose must lie within this many POS standard deviations ...
        "min_position_m": 5.0,  # ... but at least this far (horizontal) ...
        "min_height_m": 5.0,  # ... and this far (vertical) ...
        "min_rotation_deg": 10.0,  # ... and within this angle of the POS attitude
        # and jointly: the squared normalized differences (horizontal 2, vertical 1, rotation 3 degrees of
        # freedom, standard deviations at least the floors above / prior_sigmas) below this chi-square
        # quantile (6 dof, 99.9 %): a pose off in several ways at once is no longer accepted
        "prior_chi2": 22.46,
        # keep the matches that agree with the PnP pose when enough do (min_inliers, min_inlier_ratio),
        # even when the pose is not accepted (spread, POS): the matches are verified, the pose is not used
        "verify_on_consensus": True,
        # when the pose with the most inliers disagrees with the POS, a second RANSAC keeps only the
        # hypotheses that agree with it (services.reduce.prior_pnp): repeated facades can outvote the
        # true pose
        "prior_gated": True,
        "seed": 0,
    },
    # aerial points observed in every aerial image that sees them (services.reduce.tracks: guided
    # matching with the matching features' descriptors), so a link reaches all their aerial images
    "tracks": dict(tracks_default_conf),
    "fundamental": {"enabled": True, "threshold": 3.0, "confidence": 0.999, "max_iters": 10000},
    "min_pair_matches": 1,  # verified pairs with fewer matches are written without inliers
    "unverified": "drop",  # ground images without an accepted pose: "drop" or "fundamental" (F-RANSAC only)
}
