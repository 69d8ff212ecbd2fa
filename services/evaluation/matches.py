"""Match quality against ground truth: NIM, NCM, GT-correct matches, precision and NMP per method.

Pairs are the co-visible aerial-ground pairs of `gt/covisible.csv`, oriented aerial first.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import cv2
import numpy as np

from services.colmap_model import Camera, Pose
from shared.matchfile import MatchFile

from .common import DepthMaps, EvaluationError, lookup_depth, read_covisible, read_gt_model, require_scene

logger = logging.getLogger(__name__)

default_conf = {
    "min_overlap": 0.05,  # pairs of gt/covisible.csv with at least this overlap are evaluated
    "ransac_px": 3.0,  # evaluator's own F-RANSAC threshold (when the match file stores no inliers)
    "ransac_confidence": 0.999,
    "ransac_max_iters": 10000,
    "gt_px": 3.0,  # max reprojection error of a GT-correct match, in each image (full resolution)
    "occlusion_rel": 0.01,  # visible iff |z - depth| <= occlusion_rel * depth + occlusion_abs
    "occlusion_abs": 0.2,  # metres
    "depth_interp": "bilinear",  # 'bilinear' (continuity-checked, nearest across edges) or 'nearest'
    "nmp_min_correct": 15,  # a pair is matched (NMP) with at least this many GT-correct matches
}

PER_PAIR_FIELDS = ("aerial", "ground", "overlap", "nim", "ncm", "gt_correct", "precision")


def _transfer(
    kp_s: np.ndarray,
    cam_s: Camera,
    pose_s: Pose,
    depth_s: np.ndarray,
    cam_t: Camera,
    pose_t: Pose,
    depth_t: np.ndarray,
    interp: str,
    occ_rel: float,
    occ_abs: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Move source keypoints into the target image through the true depth: (uv (N, 2), visible (N,))."""
    d_s = lookup_depth(depth_s, kp_s, interp)
    X = pose_s.unproject(cam_s.K, kp_s, d_s)
    uv, z = pose_t.project(cam_t.K, X)
    d_t = lookup_depth(depth_t, uv, interp)
    visible = (d_s > 0) & (z > 0) & (d_t > 0) & (np.abs(z - d_t) <= occ_rel * d_t + occ_abs)
    return uv, visible


def gt_correct_mask(
    kp_a: np.ndarray,
    kp_b: np.ndarray,
    cam_a: Camera,
    pose_a: Pose,
    depth_a: np.ndarray,
    cam_b: Camera,
    pose_b: Pose,
    depth_b: np.ndarray,
    px: float = 3.0,
    interp: str = "bilinear",
    occ_rel: float = 0.01,
    occ_abs: float = 0.2,
) -> np.ndarray:
    """Which matches kp_a[i] <-> kp_b[i] (COLMAP pixels, full resolution) are correct under ground truth.

    A match is correct iff, in both directions (a -> b and b -> a): the source keypoint has a true
    depth (depth map != 0 at it), its unprojected 3D point projects in front of the target camera and
    inside the target image, is not occluded there (its z within occ_rel * depth + occ_abs of the
    target depth map at the projection: 1 % + 0.2 m by default), and lands within `px` pixels of the
    matched keypoint. Depths are looked up per `services.evaluation.common.lookup_depth` ('nearest'
    pixel, or 'bilinear' on continuous surfaces with nearest across depth edges). Intrinsics are used
    without distortion (K only), as synthetic scenes are PINHOLE.
    """
    kp_a = np.asarray(kp_a, np.float64).reshape(-1, 2)
    kp_b = np.asarray(kp_b, np.float64).reshape(-1, 2)
    if len(kp_a) != len(kp_b):
        raise ValueError(f"{len(kp_a)} keypoints in a but {len(kp_b)} in b")
    if len(kp_a) == 0:
        return np.zeros(0, bool)
    args = (interp, occ_rel, occ_abs)
    uv_ab, vis_ab = _transfer(kp_a, cam_a, pose_a, depth_a, cam_b, pose_b, depth_b, *args)
    uv_ba, vis_ba = _transfer(kp_b, cam_b, pose_b, depth_b, cam_a, pose_a, depth_a, *args)
    err_ab = np.linalg.norm(uv_ab - kp_b, axis=1)
    err_ba = np.linalg.norm(uv_ba - kp_a, axis=1)
    with np.errstate(invalid="ignore"):
        return vis_ab & vis_ba & (err_ab <= px) & (err_ba <= px)


def ransac_inliers(
    kp0: np.ndarray, kp1: np.ndarray, px: float = 3.0, confidence: float = 0.999, max_iters: int = 10000
) -> np.ndarray:
    """Inliers of a fundamental-matrix MAGSAC++ (deterministic: RNG seed 0); none below 8 matches."""
    if len(kp0) < 8:
        return np.zeros(len(kp0), bool)
    cv2.setRNGSeed(0)
    try:
        _, mask = cv2.findFundamentalMat(
            np.asarray(kp0, np.float64),
            np.asarray(kp1, np.float64),
            cv2.USAC_MAGSAC,
            px,
            confidence,
            max_iters,
        )
    except cv2.error as e:
        logger.debug("F-RANSAC failed: %s", e)
        mask = None
    if mask is None:
        return np.zeros(len(kp0), bool)
    return mask.reshape(-1).astype(bool)


def _pair_row(aerial: str, ground: str, overlap: float, nim: int = 0, ncm: int = 0, correct: int = 0) -> dict:
    return {
        "aerial": aerial,
        "ground": ground,
        "overlap": overlap,
        "nim": nim,
        "ncm": ncm,
        "gt_correct": correct,
        "precision": correct / ncm if ncm else 0.0,
    }


def summarize(rows: list[dict], method: str, nmp_min_correct: int = 15) -> dict:
    """Summary over per-pair rows (see PER_PAIR_FIELDS)."""
    n = len(rows)
    nim = np.array([r["nim"] for r in rows], float)
    ncm = np.array([r["ncm"] for r in rows], float)
    cor = np.array([r["gt_correct"] for r in rows], float)
    prec = np.array([r["precision"] for r in rows if r["ncm"] > 0], float)
    nmp = int((cor >= nmp_min_correct).sum())

    def mean(a: np.ndarray) -> float:
        return float(a.mean()) if len(a) else 0.0

    return {
        "method": method,
        "num_pairs": n,
        "mean_nim": mean(nim),
        "mean_ncm": mean(ncm),
        "mean_gt_correct": mean(cor),
        "mean_precision": mean(prec),
        "pooled_precision": float(cor.sum() / ncm.sum()) if ncm.sum() > 0 else 0.0,
        "total_nim": int(nim.sum()),
        "total_ncm": int(ncm.sum()),
        "total_gt_correct": int(cor.sum()),
        "nmp": nmp,
        "nmp_pct": 100.0 * nmp / n if n else 0.0,
        "nmp_min_correct": nmp_min_correct,
    }


def _open_match_file(path: Path) -> MatchFile:
    if not Path(path).is_file():
        raise EvaluationError(f"match file {path} does not exist")
    try:
        return MatchFile(path, "r")
    except (OSError, ValueError) as e:
        raise EvaluationError(f"{path}: not a midview match file ({e})") from e


def _pair_counts(
    kp_a: np.ndarray,
    kp_g: np.ndarray,
    stored_inliers: np.ndarray | None,
    aerial: str,
    ground: str,
    cams: dict,
    poses: dict,
    depths: DepthMaps,
    conf: dict,
) -> tuple[np.ndarray, np.ndarray]:
    """(inlier mask over the matches, GT-correct mask over the inliers) of one pair's matched keypoints
    kp_a, kp_g (M, 2): the stored inliers, else the evaluator's F-RANSAC; GT-correct through the depths."""
    if stored_inliers is not None:
        inl = np.asarray(stored_inliers, bool)
    else:
        inl = ransac_inliers(
            kp_a, kp_g, conf["ransac_px"], conf["ransac_confidence"], conf["ransac_max_iters"]
        )
    for name in (aerial, ground):
        cam, d = cams[name], depths[name]
        if d.shape != (cam.height, cam.width):
            raise EvaluationError(f"depth map of {name} is {d.shape}, camera is {cam.width}x{cam.height}")
    correct = gt_correct_mask(
        kp_a[inl],
        kp_g[inl],
        cams[aerial],
        poses[aerial],
        depths[aerial],
        cams[ground],
        poses[ground],
        depths[ground],
        conf["gt_px"],
        conf["depth_interp"],
        conf["occlusion_rel"],
        conf["occlusion_abs"],
    )
    return inl, correct


def evaluate_matches(
    scene_dir: Path, match_file: Path, out_dir: Path | None = None, conf: dict | None = None
) -> dict:
    """Evaluate a match file on the co-visible aerial-ground pairs of a synthetic scene.

    Per pair: NIM (putative matches), NCM (RANSAC inliers: the stored `inliers` mask, else the
    evaluator's F-RANSAC, see `ransac_inliers`), GT-correct (inliers passing `gt_correct_mask` with
    conf["gt_px"]) and precision = GT-correct / NCM (0 when NCM = 0). Pairs absent from the match file
    count with zeros. Returns the summary (see `summarize`, plus scene, match file and conf); with
    out_dir writes per_pair.csv and summary.json there.
    """
    conf = {**default_conf, **(conf or {})}
    scene_dir = require_scene(Path(scene_dir), "gt/sparse", "gt/depth.h5", "gt/covisible.csv")
    cams, poses = read_gt_model(scene_dir)
    pairs = read_covisible(scene_dir / "gt" / "covisible.csv", conf["min_overlap"])
    missing = sorted({n for a, g, _ in pairs for n in (a, g)} - set(poses))
    if missing:
        raise EvaluationError(
            f"{scene_dir}: images of gt/covisible.csv missing from gt/sparse: {missing[:5]}"
        )

    rows = []
    with _open_match_file(Path(match_file)) as mf, DepthMaps(scene_dir / "gt" / "depth.h5") as depths:
        method = mf.method or Path(match_file).stem
        have_kp = set(mf.image_names())
        kp_cache: dict[str, np.ndarray] = {}

        def keypoints(name: str) -> np.ndarray:
            if name not in kp_cache:
                kp_cache[name] = mf.keypoints(name).astype(np.float64)
            return kp_cache[name]

        for aerial, ground, overlap in pairs:
            pm = mf.get_pair(aerial, ground) if {aerial, ground} <= have_kp else None
            if pm is None or len(pm.matches) == 0:
                rows.append(_pair_row(aerial, ground, overlap))
                continue
            kp_a, kp_g = keypoints(aerial)[pm.matches[:, 0]], keypoints(ground)[pm.matches[:, 1]]
            inl, correct = _pair_counts(kp_a, kp_g, pm.inliers, aerial, ground, cams, poses, depths, conf)
            rows.append(
                _pair_row(aerial, ground, overlap, len(pm.matches), int(inl.sum()), int(correct.sum()))
            )

    summary = summarize(rows, method, conf["nmp_min_correct"])
    summary.update(scene=str(scene_dir), match_file=str(match_file), conf=conf)
    logger.info(
        "%s: %d pairs, mean NCM %.1f, GT-correct %.1f, precision %.3f, NMP %d (%.1f %%)",
        method,
        summary["num_pairs"],
        summary["mean_ncm"],
        summary["mean_gt_correct"],
        summary["mean_precision"],
        summary["nmp"],
        summary["nmp_pct"],
    )
    if out_dir is not None:
        write_outputs(Path(out_dir), rows, summary)
    return summary


def pair_bound(
    kp_a: np.ndarray,
    kp_g: np.ndarray,
    cam_a: Camera,
    pose_a: Pose,
    depth_a: np.ndarray,
    cam_g: Camera,
    pose_g: Pose,
    depth_g: np.ndarray,
    conf: dict,
) -> int:
    """The most GT-correct one-to-one matches any matcher could find between two keypoint sets: a
    maximum bipartite matching over the keypoint pairs that pass `gt_correct_mask`."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching
    from scipy.spatial import cKDTree

    if len(kp_a) == 0 or len(kp_g) == 0:
        return 0
    args = (conf["depth_interp"], conf["occlusion_rel"], conf["occlusion_abs"])
    uv, vis = _transfer(kp_g, cam_g, pose_g, depth_g, cam_a, pose_a, depth_a, *args)
    near = cKDTree(kp_a).query_ball_point(np.where(vis[:, None], uv, -1e9), r=conf["gt_px"])
    cand = np.array([(j, i) for i, js in enumerate(near) for j in js], np.int64).reshape(-1, 2)
    if len(cand) == 0:
        return 0
    ok = gt_correct_mask(
        kp_a[cand[:, 0]],
        kp_g[cand[:, 1]],
        cam_a,
        pose_a,
        depth_a,
        cam_g,
        pose_g,
        depth_g,
        conf["gt_px"],
        *args,
    )
    cand = cand[ok]
    if len(cand) == 0:
        return 0
    graph = csr_matrix((np.ones(len(cand)), (cand[:, 1], cand[:, 0])), shape=(len(kp_g), len(kp_a)))
    return int((maximum_bipartite_matching(graph, perm_type="column") >= 0).sum())


def keypoint_bound(scene_dir: Path, match_file: Path, conf: dict | None = None) -> dict:
    """Upper bound of GT-correct matches with the keypoints of a match file: per co-visible pair the
    maximum one-to-one matching among its keypoint pairs that are GT-correct (`pair_bound`). No matcher
    that outputs those keypoints can do better; summed over the pairs, with the NMP it would allow."""
    conf = {**default_conf, **(conf or {})}
    scene_dir = require_scene(Path(scene_dir), "gt/sparse", "gt/depth.h5", "gt/covisible.csv")
    cams, poses = read_gt_model(scene_dir)
    pairs = read_covisible(scene_dir / "gt" / "covisible.csv", conf["min_overlap"])
    per = []
    with _open_match_file(Path(match_file)) as mf, DepthMaps(scene_dir / "gt" / "depth.h5") as depths:
        have = set(mf.image_names())
        for a, g, _ in pairs:
            if not {a, g} <= have:
                per.append(0)
                continue
            kp_a, kp_g = mf.keypoints(a).astype(np.float64), mf.keypoints(g).astype(np.float64)
            per.append(
                pair_bound(kp_a, kp_g, cams[a], poses[a], depths[a], cams[g], poses[g], depths[g], conf)
            )
    per_a = np.array(per, float)
    return {
        "num_pairs": len(pairs),
        "total": int(per_a.sum()),
        "mean": float(per_a.mean()) if len(per_a) else 0.0,
        "nmp": int((per_a >= conf["nmp_min_correct"]).sum()),
    }


def write_outputs(out_dir: Path, rows: list[dict], summary: dict) -> None:
    """per_pair.csv and summary.json."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "per_pair.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=PER_PAIR_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({**r, "overlap": f"{r['overlap']:.4f}", "precision": f"{r['precision']:.4f}"})
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))


def print_summary_table(
    summaries: list[dict], title: str = "Match quality (aerial-ground)", console=None
) -> None:
    """A rich table with one row per method (summaries of `evaluate_matches`)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    for col in ("method", "pairs", "NIM", "NCM", "GT-correct", "precision", "pooled", "NMP"):
        table.add_column(col, justify="left" if col == "method" else "right")
    for s in summaries:
        table.add_row(
            str(s["method"]),
            str(s["num_pairs"]),
            f"{s['mean_nim']:.1f}",
            f"{s['mean_ncm']:.1f}",
            f"{s['mean_gt_correct']:.1f}",
            f"{s['mean_precision']:.3f}",
            f"{s['pooled_precision']:.3f}",
            f"{s['nmp']} ({s['nmp_pct']:.1f}%)",
        )
    (console or Console()).print(table)


def main(conf: dict, scene_dir: Path, match_file: Path, out_dir: Path) -> Path:
    """hloc-style entry: evaluate, write the outputs to out_dir and return the summary.json path."""
    evaluate_matches(scene_dir, match_file, out_dir, conf)
    return Path(out_dir) / "summary.json"
