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
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose, read_cameras_json, read_model
from services.conf import merge_conf
from services.geometry import pose_of_image, rotation_angle_deg
from services.pos import DEFAULT_STD_ATT, DEFAULT_STD_XY, DEFAULT_STD_Z
from services.pose_uncertainty import fit_position_std
from services.prior_pnp import prior_gated_pnp, reprojection_errors
from services.tracks import complete_tracks
from services.tracks import default_conf as tracks_default_conf
from shared.logging import stage
from shared.matchfile import MatchFile, PairMatches

logger = logging.getLogger("midview.transfer")

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
        "min_inliers": 12,  # inliers of a consensus (verify_on_consensus) ...
        # ... and of an accepted pose: the covariance above sees pixel noise, not 3D points biased by a
        # blurry render; with 12 inliers a fresh demo accepted a pose 2.2 m off at a 0.10 m std (the nine
        # poses accepted with perfect views have 30 or more)
        "min_pose_inliers": 20,
        "min_inlier_ratio": 0.15,
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
        # hypotheses that agree with it (services.prior_pnp): repeated facades can outvote the true pose
        "prior_gated": True,
        "seed": 0,
    },
    # aerial points observed in every aerial image that sees them (services.tracks: guided matching with
    # the matching features' descriptors), so a link reaches all their aerial images
    "tracks": dict(tracks_default_conf),
    "fundamental": {"enabled": True, "threshold": 3.0, "confidence": 0.999, "max_iters": 10000},
    "min_pair_matches": 1,  # verified pairs with fewer matches are written without inliers
    "unverified": "drop",  # ground images without an accepted pose: "drop" or "fundamental" (F-RANSAC only)
}


# -- data -----------------------------------------------------------------------------------------
@dataclass
class ViewData:
    """What the reducer needs of one rendered view."""

    name: str
    camera: Camera
    pose: Pose
    depth: np.ndarray | None  # (H, W) z-depth, 0 = none; None: no 3D checks for this view
    keypoints: dict[str, np.ndarray]  # image name -> keypoints (render: views/NAME.png)
    pairs: list[PairMatches]  # (render, image) pairs with inliers


def image_set(name: str) -> str:
    return name.split("/", 1)[0]


# -- step 1: transfer within one view ---------------------------------------------------------------
def render_points(view: ViewData, idx: np.ndarray, conf: dict) -> np.ndarray:
    """3D points (n, 3) of render keypoints `idx` through the view's depth; NaN where the depth is
    missing or on a depth edge. All NaN when the view has no depth."""
    from services.evaluation.common import lookup_depth

    rname = next(n for n in view.keypoints if image_set(n) == "views")
    out = np.full((len(idx), 3), np.nan)
    if view.depth is None or len(idx) == 0:
        return out
    kp = view.keypoints[rname][idx].astype(np.float64)
    d = lookup_depth(view.depth, kp, conf["depth_interp"])
    ok = d > 0
    w = int(conf.get("edge_window") or 0)
    if w > 1 and ok.any():
        from scipy.ndimage import maximum_filter, minimum_filter

        dep = view.depth.astype(np.float32)
        valid = dep > 0
        lo = minimum_filter(np.where(valid, dep, np.inf), size=w)
        hi = maximum_filter(np.where(valid, dep, 0.0), size=w)
        hh, ww = dep.shape
        r = np.clip(kp[:, 1].astype(int), 0, hh - 1)
        c = np.clip(kp[:, 0].astype(int), 0, ww - 1)
        ratio = hi[r, c] / np.maximum(lo[r, c], 1e-6)
        holes = minimum_filter(valid.astype(np.uint8), size=w)[r, c] == 0
        ok &= (ratio <= conf["edge_ratio"]) & ~holes
    if ok.any():
        out[ok] = view.pose.unproject(view.camera.K, kp[ok], d[ok])
    return out


def view_observations(view: ViewData, view_index: int, conf: dict) -> dict[str, dict[str, np.ndarray]]:
    """The view's inlier matches as observations per image: arrays i (the image's keypoint), ir (the
    render keypoint), score, view and X (the render keypoint's 3D point, NaN without depth)."""
    rname = next(n for n in view.keypoints if image_set(n) == "views")
    per: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for pm in view.pairs:
        if pm.name1 == rname:
            pm = pm.swapped()
        if pm.name0 != rname or image_set(pm.name1) not in ("aerial", "ground"):
            continue
        keep = np.ones(len(pm.matches), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
        keep &= np.asarray(pm.scores) >= conf["min_score"]
        m = pm.matches[keep].astype(np.int64)
        order = np.argsort(m[:, 0], kind="stable")
        per[pm.name1] = (m[order, 0], m[order, 1], np.asarray(pm.scores, np.float32)[keep][order])
    idx = np.unique(np.concatenate([r for r, _, _ in per.values()])) if per else np.zeros(0, np.int64)
    X_all = render_points(view, idx, conf)
    out = {}
    for name, (ir, i, sc) in sorted(per.items()):
        out[name] = {
            "i": i,
            "ir": ir,
            "score": sc,
            "view": np.full(len(i), view_index, np.int64),
            "X": X_all[np.searchsorted(idx, ir)] if len(ir) else np.zeros((0, 3)),
        }
    return out


def _cat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _take(d: dict[str, np.ndarray], sel) -> dict[str, np.ndarray]:
    return {k: v[sel] for k, v in d.items()}


def link_identity(oa: dict, og: dict) -> tuple[np.ndarray, np.ndarray]:
    """The paper's transfer: observations of the same render keypoint in the same view (indices into
    oa and og)."""
    big = np.int64(1) << 32
    ka, kg = oa["view"] * big + oa["ir"], og["view"] * big + og["ir"]
    _, ia, ig = np.intersect1d(ka, kg, assume_unique=True, return_indices=True)
    return ia, ig


def pixel_rays(camera: Camera, pose: Pose, kp: np.ndarray) -> np.ndarray:
    """Unit world directions (n, 3) of the rays through pixels kp (n, 2)."""
    K = camera.K
    xy = (np.asarray(kp, float).reshape(-1, 2) - K[:2, 2]) / np.diag(K)[:2]
    d = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ pose.R  # R^T d for each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def triangulate_rays(centers: np.ndarray, dirs: np.ndarray) -> np.ndarray | None:
    """The point nearest to every ray (least squares), None when the rays are (nearly) parallel."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, dirs, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    if np.linalg.cond(A) > 1e8:
        return None
    return np.linalg.solve(A, b)


def aerial_points(
    views: list[ViewData],
    aerial_cameras: dict[str, Camera],
    aerial_poses: dict[str, Pose],
    keypoints: dict[str, np.ndarray],
    obs: dict[str, dict[str, np.ndarray]],
    conf: dict,
) -> tuple[dict[str, np.ndarray], list[list[tuple[str, int, float]]], dict]:
    """3D points of the render keypoints matched to aerial images, triangulated from the render's ray
    and the aerial images' rays (poses known: the rendered depth is only a loose check), each aerial
    observation within `aerial_px` of its projection. Returns the points (arrays view, ir, X), the aerial
    observations of each point [(aerial, keypoint, score)] and counts."""
    tc = conf["triangulation"]
    per: dict[tuple[int, int], list[tuple[str, int, float]]] = {}
    for a, o in obs.items():
        if image_set(a) != "aerial" or a not in aerial_poses:
            continue
        for v, ir, ia, sc in zip(o["view"], o["ir"], o["i"], o["score"], strict=True):
            per.setdefault((int(v), int(ir)), []).append((a, int(ia), float(sc)))
    out_v, out_ir, out_X, out_obs = [], [], [], []
    n_rej = {"aerial_reprojection": 0, "render_reprojection": 0, "angle": 0, "depth": 0}
    depth_err: dict[int, list[float]] = {}  # per view: |triangulated - rendered| / rendered depth
    cos_min = np.cos(np.radians(tc["min_angle_deg"]))
    for (v, ir), items in sorted(per.items()):
        view = views[v]
        rname = next(n for n in view.keypoints if image_set(n) == "views")
        kp_r = view.keypoints[rname][ir].astype(np.float64)
        c_r, d_r = view.pose.center, pixel_rays(view.camera, view.pose, kp_r[None])[0]
        items = sorted(items)
        for _ in range(2):  # triangulate, drop the aerial observations that disagree, once more
            cs = [c_r] + [aerial_poses[a].center for a, _, _ in items]
            ds = [d_r] + [
                pixel_rays(aerial_cameras[a], aerial_poses[a], keypoints[a][ia][None])[0]
                for a, ia, _ in items
            ]
            X = triangulate_rays(np.array(cs), np.array(ds))
            if X is None:
                items = []
                break
            good = []
            for a, ia, sc in items:
                uv, z = aerial_poses[a].project(aerial_cameras[a].K, X[None])
                if z[0] > 0 and np.linalg.norm(uv[0] - keypoints[a][ia]) <= conf["aerial_px"]:
                    good.append((a, ia, sc))
            if len(good) == len(items):
                break
            n_rej["aerial_reprojection"] += len(items) - len(good)
            items = good
            if not items:
                break
        if not items or X is None:
            continue
        uv, z = view.pose.project(view.camera.K, X[None])
        if z[0] <= 0 or np.linalg.norm(uv[0] - kp_r) > tc["render_px"]:
            n_rej["render_reprojection"] += 1
            continue
        dirs = np.array([(X - aerial_poses[a].center) for a, _, _ in items])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        if (dirs @ ((X - c_r) / np.linalg.norm(X - c_r))).min() > cos_min:
            n_rej["angle"] += 1
            continue
        if view.depth is not None and tc["depth_rel"] is not None:
            from services.evaluation.common import lookup_depth

            d = lookup_depth(view.depth, kp_r[None], "nearest")[0]
            if d > 0:
                depth_err.setdefault(v, []).append(abs(z[0] - d) / d)
            if d > 0 and abs(z[0] - d) > tc["depth_rel"] * d + tc["depth_abs"]:
                n_rej["depth"] += 1
                continue
        out_v.append(v)
        out_ir.append(ir)
        out_X.append(X)
        out_obs.append(items)
    pts = {
        "view": np.array(out_v, np.int64),
        "ir": np.array(out_ir, np.int64),
        "X": np.array(out_X, float).reshape(-1, 3),
    }
    n_rej["depth_error"] = {views[v].name: float(np.median(e)) for v, e in sorted(depth_err.items()) if e}
    return pts, out_obs, n_rej


def link_points(
    views: list[ViewData],
    pts: dict[str, np.ndarray],
    pts_obs: list[list[tuple[str, int, float]]],
    og: dict[str, np.ndarray],
    conf: dict,
) -> list[tuple[str, int, int, float, int, np.ndarray]]:
    """Links of one ground image's observations to the aerial points: a point that projects within
    `link.px` of the observation's render keypoint, in front of the rendered surface there (within
    link.visibility_rel x depth + link.visibility_abs: not hidden in that view). Any view's point may
    serve: a view low enough to match the ground image and another high enough to match the aerial one
    meet at their common 3D points. Returns [(aerial, ia, ig, score, view, X)]."""
    from scipy.spatial import cKDTree

    from services.evaluation.common import lookup_depth

    lc = conf["link"]
    out = []
    if len(pts["X"]) == 0:
        return out
    for v in sorted(set(og["view"].tolist())):
        view = views[v]
        rname = next(n for n in view.keypoints if image_set(n) == "views")
        uv, z = view.pose.project(view.camera.K, pts["X"])
        w, h = view.camera.width, view.camera.height
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if view.depth is not None:
            d = lookup_depth(view.depth, np.where(ok[:, None], uv, 0.0), "nearest")
            ok &= (d > 0) & (z <= d * (1.0 + lc["visibility_rel"]) + lc["visibility_abs"])
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            continue
        tree = cKDTree(uv[idx])
        sel = np.flatnonzero(og["view"] == v)
        kp_r = view.keypoints[rname][og["ir"][sel]].astype(np.float64)
        for k, nb in zip(sel, tree.query_ball_point(kp_r, r=lc["px"]), strict=True):
            for j in nb:
                p = idx[j]
                for a, ia, sa in pts_obs[p]:
                    out.append((a, ia, int(og["i"][k]), min(sa, float(og["score"][k])), v, pts["X"][p]))
    return out


# -- step 2: merge -------------------------------------------------------------------------------
def merge_one_to_one(cand: dict[str, np.ndarray], view_names: list[str]) -> np.ndarray:
    """Indices into `cand` of the kept correspondences: one per (ia, ig), then one-to-one, greedily in
    the order (score desc, view name, ia, ig). Deterministic and independent of the input order."""
    n = len(cand["ia"])
    if n == 0:
        return np.zeros(0, np.int64)
    vname = np.array([view_names[v] for v in cand["view"]], dtype=object)
    vrank = np.argsort(np.argsort(vname, kind="stable"), kind="stable")  # rank of the view's name
    order = np.lexsort((cand["ig"], cand["ia"], vrank, -cand["score"].astype(np.float64)))
    used_a: set[int] = set()
    used_g: set[int] = set()
    keep = []
    for k in order:
        a, g = int(cand["ia"][k]), int(cand["ig"][k])
        if a in used_a or g in used_g:
            continue
        used_a.add(a)
        used_g.add(g)
        keep.append(int(k))
    return np.array(keep, np.int64)


# -- step 3: PnP -----------------------------------------------------------------------------------


def prior_chi2(dxy: float, dz: float, drot: float, std: tuple[float, float, float], pc: dict) -> float:
    """Squared normalized difference of a pose to its POS: horizontal (m), vertical (m) and rotation
    (deg) over their standard deviations, each at least its floor (min_position_m etc.) / prior_sigmas."""
    k = pc["prior_sigmas"]
    sxy = max(std[0], pc["min_position_m"] / (k * math.sqrt(2.0)))
    sz = max(std[1], pc["min_height_m"] / k)
    satt = max(std[2], pc["min_rotation_deg"] / (k * math.sqrt(3.0)))
    return float((dxy / sxy) ** 2 + (dz / sz) ** 2 + (drot / satt) ** 2)


def prior_agreement(
    pose: Pose, prior: Pose, prior_std: tuple[float, float, float] | None, pc: dict
) -> tuple[dict, dict, list[str]]:
    """How far `pose` is from its POS `prior`: (differences, limits, reasons it disagrees). Position and
    attitude each within prior_sigmas standard deviations (or the floors), and jointly (chi-square)."""
    d = pose.center - prior.center
    dxy, dz = float(np.linalg.norm(d[:2])), float(abs(d[2]))
    drot = rotation_angle_deg(pose.R @ prior.R.T)
    sxy, sz, satt = prior_std or (DEFAULT_STD_XY, DEFAULT_STD_Z, DEFAULT_STD_ATT)
    k = pc["prior_sigmas"]
    lim_xy, lim_z = max(k * sxy * math.sqrt(2.0), pc["min_position_m"]), max(k * sz, pc["min_height_m"])
    lim_rot = max(k * satt * math.sqrt(3.0), pc["min_rotation_deg"])
    chi2 = prior_chi2(dxy, dz, drot, (sxy, sz, satt), pc)
    to_pos = {"horizontal_m": dxy, "vertical_m": dz, "rotation_deg": drot, "chi2": chi2}
    limits = {"horizontal_m": lim_xy, "vertical_m": lim_z, "rotation_deg": lim_rot}
    reasons = []
    if dxy > lim_xy:
        reasons.append(f"{dxy:.1f} m from the POS horizontally (> {lim_xy:.1f})")
    if dz > lim_z:
        reasons.append(f"{dz:.1f} m from the POS vertically (> {lim_z:.1f})")
    if drot > lim_rot:
        reasons.append(f"{drot:.1f} deg from the POS attitude (> {lim_rot:.1f})")
    if pc.get("prior_chi2") and chi2 > pc["prior_chi2"]:
        reasons.append(f"position and attitude jointly {chi2:.1f} (chi-square > {pc['prior_chi2']:.1f})")
    return to_pos, limits, reasons


def estimate_ground_pose(
    kp: np.ndarray,
    X: np.ndarray,
    camera: Camera,
    prior: Pose | None,
    prior_std: tuple[float, float, float] | None,
    conf: dict,
) -> dict:
    """PnP LO-RANSAC of one ground image with its POS as a prior. Returns a dict with `accepted`,
    `reason`, and when estimated: pose (R, t), center, inlier mask, residuals (px) of every
    correspondence, and the differences to the POS."""
    import pycolmap

    pc = conf["pnp"]
    n = len(kp)
    res: dict[str, Any] = {"num_correspondences": int(n), "accepted": False}
    if n < max(pc["min_inliers"], 4):
        res["reason"] = f"{n} correspondences (< {pc['min_inliers']})"
        return res
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = float(pc["ransac_px"])
    opts.ransac.random_seed = int(pc["seed"])
    opts.ransac.min_inlier_ratio = 0.05
    opts.ransac.max_num_trials = 20000
    cam = camera.to_pycolmap(1)
    try:
        out = pycolmap.estimate_and_refine_absolute_pose(
            np.ascontiguousarray(kp, np.float64), np.ascontiguousarray(X, np.float64), cam, opts
        )
    except Exception as e:  # pycolmap raises on degenerate input
        out = None
        logger.debug("PnP failed: %s", e)
    pose = None
    solver = "pycolmap"
    if out is not None:
        m = np.asarray(out["cam_from_world"].matrix())
        pose = Pose(m[:, :3].copy(), m[:, 3].copy())
    disagrees = pose is None or (prior is not None and bool(prior_agreement(pose, prior, prior_std, pc)[2]))
    if prior is not None and pc["prior_gated"] and disagrees:
        # the pose with the most inliers disagrees with the POS: the best one that agrees with it
        def gate(p: Pose) -> bool:
            return not prior_agreement(p, prior, prior_std, pc)[2]

        gated, _ = prior_gated_pnp(kp, X, camera.K, gate, pc["ransac_px"], seed=int(pc["seed"]))
        if gated is not None:
            pose, solver = gated, "prior-gated"
    if pose is None:
        res["reason"] = "PnP RANSAC found no pose"
        return res
    err = reprojection_errors(pose, camera.K, kp, X)
    inl = err <= pc["keep_px"]
    res["solver"] = solver
    res.update(
        R=pose.R.tolist(),
        t=pose.t.tolist(),
        center=pose.center.tolist(),
        num_inliers=int(inl.sum()),
        inlier_ratio=float(inl.mean()),
        _pose=pose,
        _inliers=inl,
        _err=err,
    )
    reasons = []
    if inl.sum() >= 3:
        # how well the inliers pin the camera centre (pixel noise: their RMS residual, at least 1 px)
        std = fit_position_std(pose, camera.K, kp[inl], X[inl])
        res["position_std_m"] = std
        if pc.get("max_position_std_m") and std > pc["max_position_std_m"]:
            reasons.append(
                f"position ill-determined by its inliers: std {std:.2f} m (> {pc['max_position_std_m']})"
            )
    if inl.any():
        span = kp[inl].max(0) - kp[inl].min(0)
        spread = float(span[0] * span[1] / (camera.width * camera.height))
        res["inlier_spread"] = spread
        if spread < pc.get("min_spread", 0.0):
            reasons.append(
                f"inliers cover {100 * spread:.1f}% of the image (< {100 * pc['min_spread']:.0f}%)"
            )
    if inl.sum() < pc["min_inliers"]:
        reasons.append(f"{int(inl.sum())} inliers (< {pc['min_inliers']})")
    elif inl.sum() < pc.get("min_pose_inliers", 0):
        reasons.append(
            f"{int(inl.sum())} inliers verify matches but are too few for a pose (< {pc['min_pose_inliers']})"
        )
    if inl.mean() < pc["min_inlier_ratio"]:
        reasons.append(f"inlier ratio {inl.mean():.2f} (< {pc['min_inlier_ratio']})")
    # enough correspondences agree on one camera: they verify the matches even where the pose itself is
    # ill-determined (clustered or planar points) and fails the spread check above or the POS checks below
    res["consensus"] = bool(inl.sum() >= pc["min_inliers"] and inl.mean() >= pc["min_inlier_ratio"])
    if prior is not None:
        to_pos, limits, prior_reasons = prior_agreement(pose, prior, prior_std, pc)
        res.update(to_pos=to_pos, limits=limits)
        reasons += prior_reasons
    res["accepted"] = not reasons
    res["reason"] = "; ".join(reasons) if reasons else "ok"
    return res


def trusted_depth_views(view_names: list[str], depth_error: dict[str, float], pc: dict) -> list[int]:
    """Indices of the views whose rendered depth lifts ground matches to 3D: median relative difference
    to their triangulated aerial points <= depth_trust. A view without aerial points to measure (a low
    view that matches only the ground image) is trusted when the renderer is: the median over the
    measured views (at least min_trust_views of them) is within depth_trust."""
    tol = pc["depth_trust"]
    measured = list(depth_error.values())
    renderer_ok = len(measured) >= pc["min_trust_views"] and float(np.median(measured)) <= tol
    return [
        i for i, n in enumerate(view_names) if (depth_error[n] <= tol if n in depth_error else renderer_ok)
    ]


# -- inputs --------------------------------------------------------------------------------------
def load_views(
    views_json: str | Path, match_files: list[str | Path], with_depth: bool = True
) -> tuple[list[ViewData], dict]:
    """The rendered views (views/views.json, with depths) and their match files, sorted by view name."""
    from services.matching.views import read_view_matches
    from services.views import read_render

    views_json = Path(views_json)
    doc = json.loads(views_json.read_text())
    entries = {v["name"]: v for v in doc["views"]}
    out = []
    for path in match_files:
        name, kps, pairs, _ = read_view_matches(path)
        v = entries.get(name)
        if v is None:
            logger.warning("%s: view %s is not in %s; skipped", path, name, views_json)
            continue
        depth = None
        if with_depth:
            try:
                depth = read_render(views_json.parent, v)[1]
            except FileNotFoundError:
                logger.warning("view %s has no depth: no 3D checks for its matches", name)
        out.append(
            ViewData(
                name,
                Camera(**v["camera"]),
                Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float)),
                depth,
                kps,
                pairs,
            )
        )
    return sorted(out, key=lambda v: v.name), doc


def load_aerial_features(path: str | Path, names: list[str]) -> dict[str, dict[str, np.ndarray]]:
    """Keypoints and descriptors of the aerial images `names` found in a feature cache."""
    import h5py

    from services.features import load_features

    path = Path(path)
    if not path.is_file():
        logger.warning("no feature cache %s: aerial tracks are not completed", path)
        return {}
    with h5py.File(path, "r") as h5:
        present = [n for n in names if n in h5]
    return {n: load_features(path, n) for n in present}


def ground_priors(
    pos: str | Path | list, georef: str | Path
) -> tuple[dict[str, Pose], dict[str, tuple[float, float, float]]]:
    """Ground POS poses in the aerial model frame and their standard deviations."""
    from services.pos import read_pos
    from services.sfm.georef import read_georef_frame
    from services.viewpoints import pos_in_frame

    records = read_pos(pos) if isinstance(pos, str | Path) else list(pos)
    frame = read_georef_frame(georef)
    poses, std = {}, {}
    for n, (pose, _, r) in pos_in_frame(records, frame).items():
        if image_set(n) != "ground" or pose is None:
            continue
        poses[n] = pose
        std[n] = r.std_or_default()
    return poses, std


# -- main ----------------------------------------------------------------------------------------
def reduce_views(
    views: list[ViewData],
    aerial_cameras: dict[str, Camera],
    aerial_poses: dict[str, Pose],
    ground_camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, tuple[float, float, float]],
    conf: dict | None = None,
    aerial_features: dict[str, dict[str, np.ndarray]] | None = None,
) -> tuple[dict[tuple[str, str], dict], dict[str, np.ndarray], dict[str, dict], dict]:
    """The reducer on loaded views. Returns (pairs, keypoints, ground poses, stats); pairs maps
    (aerial, ground) to arrays matches (M, 2), scores, inliers, views (index into stats["views"]) and X
    (the 3D point of each match, NaN without 3D). `aerial_features` (image name -> keypoints and
    descriptors of the matching features) lets the aerial points be completed over all those images."""
    conf = merge_conf(default_conf, conf)
    views = sorted(views, key=lambda v: v.name)
    view_names = [v.name for v in views]
    if len(set(view_names)) != len(view_names):
        raise ValueError("view names must be unique")
    keypoints: dict[str, np.ndarray] = {}
    for v in views:
        for n, kp in v.keypoints.items():
            if image_set(n) == "views":
                continue
            if n in keypoints:
                if keypoints[n].shape != kp.shape:
                    raise ValueError(
                        f"{v.name}: keypoints of {n} differ from another view's (feature caches?)"
                    )
            else:
                keypoints[n] = kp
    for n, f in sorted((aerial_features or {}).items()):
        if n in keypoints and keypoints[n].shape != f["keypoints"].shape:
            raise ValueError(f"keypoints of {n} differ between the match files and the feature cache")
        keypoints.setdefault(n, np.asarray(f["keypoints"]))
    # 1. observations of every image through every view
    parts: dict[str, list[dict]] = {}
    for i, v in enumerate(views):
        for name, o in view_observations(v, i, conf).items():
            parts.setdefault(name, []).append(o)
    obs = {n: _cat(p) for n, p in sorted(parts.items())}
    aerials = sorted(n for n in obs if image_set(n) == "aerial")
    grounds = sorted(n for n in obs if image_set(n) == "ground")
    use_3d = bool(conf["pnp"]["enabled"]) and any(a in aerial_poses for a in aerials)
    stats: dict[str, Any] = {"views": view_names}
    # 2. candidate links per aerial-ground pair
    cands: dict[tuple[str, str], list[dict[str, np.ndarray]]] = {}
    if use_3d:
        pts, pts_obs, rej = aerial_points(views, aerial_cameras, aerial_poses, keypoints, obs, conf)
        stats["aerial_points"] = len(pts["X"])
        stats["aerial_rejected"] = rej
        if aerial_features and conf["tracks"]["enabled"]:
            pts_obs, stats["tracks"] = complete_tracks(
                conf["tracks"],
                pts["X"],
                pts_obs,
                aerial_cameras,
                aerial_poses,
                {n: f["keypoints"] for n, f in aerial_features.items()},
                {n: f["descriptors"] for n, f in aerial_features.items()},
            )
        if conf["link"]["mode"] == "identity":  # only the same render keypoint (the paper)
            big = np.int64(1) << 32
            pkey = pts["view"] * big + pts["ir"]
        n_links = 0
        for g in grounds:
            og = obs[g]
            if conf["link"]["mode"] == "identity":
                keep = np.isin(og["view"] * big + og["ir"], pkey)
                og = _take(og, keep)
                sub = {k: v[np.isin(pkey, og["view"] * big + og["ir"])] for k, v in pts.items()}
                sub_obs = [pts_obs[k] for k in np.flatnonzero(np.isin(pkey, og["view"] * big + og["ir"]))]
                links = link_points(views, sub, sub_obs, og, merge_conf(conf, {"link": {"px": 1e-3}}))
            else:
                links = link_points(views, pts, pts_obs, og, conf)
            n_links += len(links)
            for a, ia, ig, sc, v, X in links:
                cands.setdefault((a, g), []).append({"ia": ia, "ig": ig, "score": sc, "view": v, "X": X})
        stats["links"] = n_links
    else:  # no geometry: the paper's transfer on the keypoint tables alone
        for g in grounds:
            for a in aerials:
                ia, ig = link_identity(obs[a], obs[g])
                for x, y in zip(ia, ig, strict=True):
                    cands.setdefault((a, g), []).append(
                        {
                            "ia": int(obs[a]["i"][x]),
                            "ig": int(obs[g]["i"][y]),
                            "score": float(min(obs[a]["score"][x], obs[g]["score"][y])),
                            "view": int(obs[g]["view"][y]),
                            "X": np.full(3, np.nan),
                        }
                    )
        stats["links"] = int(sum(len(c) for c in cands.values()))
    merged: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for key in sorted(cands):
        rows = cands[key]
        c = {
            "ia": np.array([r["ia"] for r in rows], np.int64),
            "ig": np.array([r["ig"] for r in rows], np.int64),
            "score": np.array([r["score"] for r in rows], np.float32),
            "view": np.array([r["view"] for r in rows], np.int64),
            "X": np.array([r["X"] for r in rows], float).reshape(-1, 3),
        }
        keep = merge_one_to_one(c, view_names)
        merged[key] = _take(c, keep)
    # 3. PnP per ground image on its 2D-3D correspondences
    poses: dict[str, dict] = {}
    verified: dict[tuple[str, str], np.ndarray] = {k: np.ones(len(m["ia"]), bool) for k, m in merged.items()}
    if use_3d:
        for g in grounds:
            keys = [k for k in merged if k[1] == g]
            ig = np.concatenate([merged[k]["ig"] for k in keys]) if keys else np.zeros(0, np.int64)
            X = np.concatenate([merged[k]["X"] for k in keys]) if keys else np.zeros((0, 3))
            sc = np.concatenate([merged[k]["score"] for k in keys]) if keys else np.zeros(0, np.float32)
            from_depth = np.zeros(len(ig), bool)
            dp = conf["pnp"]["depth_points"]
            if dp:  # also render-ground matches lifted by the rendered depth (of the views it can be trusted)
                og = obs[g]
                has_x = np.isfinite(og["X"]).all(1)
                errors = stats["aerial_rejected"]["depth_error"]
                trusted = np.isin(og["view"], trusted_depth_views(view_names, errors, conf["pnp"]))
                if dp == "trusted":
                    has_x &= trusted
                ig = np.concatenate([ig, og["i"][has_x]])
                X = np.concatenate([X, og["X"][has_x]])
                sc = np.concatenate([sc, og["score"][has_x]])
                from_depth = np.concatenate([from_depth, trusted[has_x]])
            # one 3D point per ground keypoint: the best-scored one
            order = np.lexsort((-sc.astype(np.float64), ig))
            first = np.ones(len(order), bool)
            first[1:] = ig[order][1:] != ig[order][:-1]
            sel = order[first]
            kp = keypoints[g][ig[sel]].astype(np.float64)
            res = estimate_ground_pose(kp, X[sel], ground_camera, priors.get(g), prior_std.get(g), conf)
            pose = res.pop("_pose", None)
            inl = res.pop("_inliers", None)
            res.pop("_err", None)
            if inl is not None:  # inliers whose 3D point is the rendered depth of a view trusted for it
                res["trusted_depth_inliers"] = int((from_depth[sel] & inl).sum())
            poses[g] = res
            for key in keys:
                m = merged[key]
                if res["accepted"] or (conf["pnp"]["verify_on_consensus"] and res.get("consensus")):
                    uv, z = pose.project(ground_camera.K, m["X"])
                    err = np.where(z > 0, np.linalg.norm(uv - keypoints[g][m["ig"]], axis=1), np.inf)
                    verified[key] = err <= conf["pnp"]["keep_px"]
                elif conf["unverified"] == "fundamental":
                    verified[key] = np.ones(len(m["ia"]), bool)
                else:
                    verified[key] = np.zeros(len(m["ia"]), bool)
    # 4. F-RANSAC per pair
    from services.matching.direct import verify_fundamental

    fc = conf["fundamental"]
    pairs = {}
    for key in sorted(merged):
        a, g = key
        m = merged[key]
        inl = verified[key]
        if fc["enabled"] and inl.sum() >= 8:
            mm = np.stack([m["ia"][inl], m["ig"][inl]], 1)
            f_inl = verify_fundamental(
                keypoints[a],
                keypoints[g],
                mm,
                {"threshold": fc["threshold"], "confidence": fc["confidence"], "max_iters": fc["max_iters"]},
            )
            inl = inl.copy()
            inl[np.flatnonzero(inl)] = f_inl
        if inl.sum() < conf["min_pair_matches"]:
            inl = np.zeros_like(inl)
        pairs[key] = {
            "matches": np.stack([m["ia"], m["ig"]], 1).astype(np.int32).reshape(-1, 2),
            "scores": m["score"].astype(np.float32),
            "inliers": inl,
            "views": m["view"].astype(np.int32),
            "X": m["X"],
        }
    stats["num_pairs"] = len(pairs)
    stats["putative"] = int(sum(len(p["matches"]) for p in pairs.values()))
    stats["verified"] = int(sum(int(p["inliers"].sum()) for p in pairs.values()))
    stats["ground_accepted"] = sorted(g for g, r in poses.items() if r["accepted"])
    return pairs, keypoints, poses, stats


def write_match_file(
    path: str | Path,
    pairs: dict[tuple[str, str], dict],
    keypoints: dict[str, np.ndarray],
    sizes: dict[str, tuple[int, int]],
    view_names: list[str],
    method: str = "midview",
) -> Path:
    with MatchFile(path, "w", method=method) as mf:
        names = sorted({n for k in pairs for n in k})
        for n in names:
            mf.add_keypoints(n, keypoints[n], sizes[n])
        for v in view_names:
            mf.view_index(v)
        for (a, g), p in sorted(pairs.items()):
            mf.add_pair(PairMatches(a, g, p["matches"], p["scores"], p["inliers"], p.get("views")))
    return Path(path)


def pose_document(poses: dict[str, dict], georef: str | Path | None) -> dict:
    """ground_poses.json: PnP poses in the model frame (and WGS84 with the georef frame)."""
    frame = None
    if georef is not None:
        from services.sfm.georef import read_georef_frame

        frame = read_georef_frame(georef)
    out = {}
    for g, r in sorted(poses.items()):
        d = dict(r)
        if frame is not None and "center" in r:
            lat, lon, h = frame.to_wgs84(np.asarray(r["center"], float)[None])
            d["wgs84"] = {"lat": float(lat[0]), "lon": float(lon[0]), "h": float(h[0])}
        out[g] = d
    doc = {"frame": None, "images": out}
    if frame is not None:
        doc["frame"] = {"type": "ENU", "lat0": frame.lat0, "lon0": frame.lon0, "h0": frame.h0}
    return doc


def main(
    conf: dict | None,
    views_json: str | Path,
    match_files: list[str | Path],
    sparse: str | Path,
    pos: str | Path,
    cameras: str | Path | dict[str, Camera],
    georef: str | Path,
    out_dir: str | Path,
    database: bool = True,
    features: str | Path | None = None,
) -> Path:
    """Run the reducer; returns out_dir/matches.h5 (see the module docstring for the other outputs).
    `features`: the matching features' cache (services.features), for the aerial track completion."""
    conf = merge_conf(default_conf, conf)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with stage("reduce", logger):
        t0 = time.perf_counter()
        views, _ = load_views(views_json, sorted(Path(p) for p in match_files))
        cams = read_cameras_json(cameras) if isinstance(cameras, str | Path) else dict(cameras)
        a_cams, a_poses = read_model(sparse)
        priors, prior_std = ground_priors(pos, georef)
        a_feats = load_aerial_features(features, sorted(a_poses)) if features is not None else None
        pairs, keypoints, poses, stats = reduce_views(
            views, a_cams, a_poses, cams["ground"], priors, prior_std, conf, a_feats
        )
        sizes = {}
        for n in keypoints:
            s = image_set(n)
            if s in cams:
                sizes[n] = (cams[s].width, cams[s].height)
        match_path = write_match_file(out_dir / "matches.h5", pairs, keypoints, sizes, stats["views"])
        (out_dir / "ground_poses.json").write_text(json.dumps(pose_document(poses, georef), indent=1))
        if database:
            from services.colmap_db import export_to_database

            export_to_database(match_path, out_dir / "database.db", cams, only_inliers=True)
        per_pair = {
            f"{a} {g}": {"putative": int(len(p["matches"])), "verified": int(p["inliers"].sum())}
            for (a, g), p in sorted(pairs.items())
        }
        report = {
            **{k: v for k, v in stats.items() if k != "views"},
            "num_views": len(stats["views"]),
            "ground_poses": {
                g: {
                    k: r.get(k)
                    for k in ("accepted", "reason", "num_correspondences", "num_inliers", "to_pos")
                }
                for g, r in sorted(poses.items())
            },
            "pairs": per_pair,
            "seconds": time.perf_counter() - t0,
            "conf": conf,
        }
        (out_dir / "report.json").write_text(json.dumps(report, indent=1))
        logger.info(
            "%d views: %d aerial points (rejected: %s), %d links; %d pairs, %d putative, %d verified; "
            "ground poses accepted %d/%d",
            len(views),
            stats.get("aerial_points", 0),
            {k: v for k, v in stats.get("aerial_rejected", {}).items() if k != "depth_error"},
            stats["links"],
            stats["num_pairs"],
            stats["putative"],
            stats["verified"],
            len(stats["ground_accepted"]),
            len(poses),
        )
    return match_path


# -- direct matches (baselines) ----------------------------------------------------------------------
def lift_aerial_keypoints(
    rec, name: str, kps: np.ndarray, radius_px: float = 12.0, k: int = 5, max_ratio: float = 1.1
) -> np.ndarray:
    """3D points (N, 3) of aerial keypoints from the depths of the aerial model's points seen in that
    image (median of the k nearest projections within radius_px, if they agree); NaN elsewhere."""
    from scipy.spatial import cKDTree

    out = np.full((len(kps), 3), np.nan)
    img = rec.find_image_with_name(name)
    if img is None or not img.has_pose or len(kps) == 0:
        return out
    ids = [p.point3D_id for p in img.points2D if p.has_point3D()]
    if len(ids) < k:
        return out
    X = np.array([rec.points3D[i].xyz for i in ids])
    pose = pose_of_image(img)
    K = np.asarray(img.camera.calibration_matrix())
    uv, z = pose.project(K, X)
    ok = z > 0
    tree = cKDTree(uv[ok])
    zs = z[ok]
    d, j = tree.query(np.asarray(kps, float), k=k, distance_upper_bound=radius_px)
    for n in range(len(kps)):
        sel = j[n][np.isfinite(d[n])]
        if len(sel) < 3:
            continue
        zz = zs[sel]
        if zz.max() / zz.min() > max_ratio:
            continue
        out[n] = pose.unproject(K, np.asarray(kps[n], float)[None], np.array([np.median(zz)]))[0]
    return out


def localize_direct(
    conf: dict | None,
    match_file: str | Path,
    sparse: str | Path,
    pos: str | Path,
    cameras: str | Path | dict[str, Camera],
    georef: str | Path,
    out_dir: str | Path,
) -> Path:
    """The reducer's PnP check for a direct match file (a baseline): its aerial keypoints are lifted to 3D
    with the aerial model's points, each ground image localized by PnP with its POS as a prior, and the
    matches consistent with the pose kept. Writes out_dir/matches.h5 and ground_poses.json as `main` does,
    so that services.combined_sfm can reconstruct with them (the same procedure for every method)."""
    import pycolmap

    conf = merge_conf(default_conf, conf)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cams = read_cameras_json(cameras) if isinstance(cameras, str | Path) else dict(cameras)
    rec = pycolmap.Reconstruction(str(sparse))
    priors, prior_std = ground_priors(pos, georef)
    with MatchFile(match_file, "r") as mf:
        kps = {n: mf.keypoints(n) for n in mf.image_names()}
        sizes = {n: mf.image_size(n) for n in kps}
        pms = list(mf.iter_pairs())
    lifted: dict[str, np.ndarray] = {}
    per_ground: dict[str, list] = {}
    for pm in pms:
        if image_set(pm.name0) != "aerial":
            pm = pm.swapped()
        a, g = pm.name0, pm.name1
        inl = np.ones(len(pm.matches), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
        if a not in lifted:
            lifted[a] = lift_aerial_keypoints(rec, a, kps[a])
        m = pm.matches[inl]
        per_ground.setdefault(g, []).append((a, m, pm.scores[inl], lifted[a][m[:, 0]]))
    pairs, poses = {}, {}
    for g, items in sorted(per_ground.items()):
        kp = np.concatenate([kps[g][m[:, 1]] for _, m, _, _ in items]).astype(np.float64)
        X = np.concatenate([x for _, _, _, x in items])
        ok = np.isfinite(X).all(1)
        res = estimate_ground_pose(kp[ok], X[ok], cams["ground"], priors.get(g), prior_std.get(g), conf)
        pose = res.pop("_pose", None)
        res.pop("_inliers", None)
        res.pop("_err", None)
        poses[g] = res
        for a, m, sc, x in items:
            keep = np.zeros(len(m), bool)
            if res["accepted"] or (conf["pnp"]["verify_on_consensus"] and res.get("consensus")):
                good = np.isfinite(x).all(1)
                uv, z = pose.project(cams["ground"].K, np.where(good[:, None], x, 0.0))
                err = np.linalg.norm(uv - kps[g][m[:, 1]], axis=1)
                keep = good & (z > 0) & (err <= conf["pnp"]["keep_px"])
            pairs[(a, g)] = {
                "matches": m.astype(np.int32),
                "scores": np.asarray(sc, np.float32),
                "inliers": keep,
            }
    path = write_match_file(out_dir / "matches.h5", pairs, kps, sizes, [], method="direct+pnp")
    (out_dir / "ground_poses.json").write_text(json.dumps(pose_document(poses, georef), indent=1))
    return path
