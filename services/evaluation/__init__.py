"""Evaluation against the ground truth of synthetic scenes: match quality and reconstructions."""

from .common import EvaluationError, lookup_depth, read_covisible
from .matches import evaluate_matches, gt_correct_mask, keypoint_bound, print_summary_table, ransac_inliers
from .sfm import evaluate_sfm, print_sfm_table

__all__ = [
    "EvaluationError",
    "evaluate_matches",
    "evaluate_sfm",
    "gt_correct_mask",
    "keypoint_bound",
    "lookup_depth",
    "print_sfm_table",
    "print_summary_table",
    "ransac_inliers",
    "read_covisible",
]
