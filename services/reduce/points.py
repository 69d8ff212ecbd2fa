"""Step 2 of the reducer: aerial points triangulated from the render's ray and the aerial rays, and the
links of each ground observation to the aerial points it sees (aerial-ground matches with their 3D
point), or without aerial poses the paper's transfer on the keypoint tables alone."""

from __future__ import annotations

from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose
from services.conf import merge_conf
from services.reduce.observations import ViewData, image_set, link_identity, take
from services.reduce.tracks import complete_tracks

Candidates = dict[tuple[str, str], list[dict[str, Any]]]


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
    for (v, ir), items in sorted(per.items()):
        view = views[v]
        rname = next(n for n in view.keypoints if image_set(n) == "views")
        kp_r = view.keypoints[rname][ir].astype(np.float64)
        X, items = _triangulate(
            view, kp_r, sorted(items), aerial_cameras, aerial_poses, keypoints, conf, n_rej
        )
        if X is None or not _point_checks(
            view, kp_r, X, items, aerial_poses, tc, n_rej, depth_err.setdefault(v, [])
        ):
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


def _triangulate(
    view: ViewData,
    kp_r: np.ndarray,
    items: list[tuple[str, int, float]],
    aerial_cameras: dict[str, Camera],
    aerial_poses: dict[str, Pose],
    keypoints: dict[str, np.ndarray],
    conf: dict,
    n_rej: dict,
) -> tuple[np.ndarray | None, list[tuple[str, int, float]]]:
    """(X, the aerial observations kept) of one render keypoint kp_r: triangulated from the render's ray
    and the aerial rays, the aerial observations farther than aerial_px from X's projection dropped and
    X triangulated once more; X None when the rays are parallel or no aerial observation is left."""
    c_r, d_r = view.pose.center, pixel_rays(view.camera, view.pose, kp_r[None])[0]
    X = None
    for _ in range(2):
        cs = [c_r] + [aerial_poses[a].center for a, _, _ in items]
        ds = [d_r] + [
            pixel_rays(aerial_cameras[a], aerial_poses[a], keypoints[a][ia][None])[0] for a, ia, _ in items
        ]
        X = triangulate_rays(np.array(cs), np.array(ds))
        if X is None:
            return None, []
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
            return None, []
    return X, items


def _point_checks(
    view: ViewData,
    kp_r: np.ndarray,
    X: np.ndarray,
    items: list[tuple[str, int, float]],
    aerial_poses: dict[str, Pose],
    tc: dict,
    n_rej: dict,
    depth_err: list[float],
) -> bool:
    """Whether X reprojects onto its render keypoint, is seen under a real angle by the render and an
    aerial image, and agrees loosely with the rendered depth (each failure counted in n_rej; the
    relative depth difference appended to depth_err)."""
    from services.geometry import lookup_depth

    uv, z = view.pose.project(view.camera.K, X[None])
    if z[0] <= 0 or np.linalg.norm(uv[0] - kp_r) > tc["render_px"]:
        n_rej["render_reprojection"] += 1
        return False
    c_r = view.pose.center
    dirs = np.array([(X - aerial_poses[a].center) for a, _, _ in items])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    if (dirs @ ((X - c_r) / np.linalg.norm(X - c_r))).min() > np.cos(np.radians(tc["min_angle_deg"])):
        n_rej["angle"] += 1
        return False
    if view.depth is not None and tc["depth_rel"] is not None:
        d = lookup_depth(view.depth, kp_r[None], "nearest")[0]
        if d > 0:
            depth_err.append(abs(z[0] - d) / d)
        if d > 0 and abs(z[0] - d) > tc["depth_rel"] * d + tc["depth_abs"]:
            n_rej["depth"] += 1
            return False
    return True


def link_points(
    views: list[ViewData],
    pts: dict[str, np.ndarray],
    pts_obs: list[list[tuple[str, int, float]]],
    og: dict[str, np.ndarray],
    conf: dict,
) -> list[tuple[str, int, int, float, int, np.ndarray, int]]:
    """Links of one ground image's observations to the aerial points: a point that projects within
    `link.px` of the observation's render keypoint, in front of the rendered surface there (within
    link.visibility_rel x depth + link.visibility_abs: not hidden in that view). Any view's point may
    serve: a view low enough to match the ground image and another high enough to match the aerial one
    meet at their common 3D points. Returns [(aerial, ia, ig, score, view, X, aerial observations of X)]."""
    from scipy.spatial import cKDTree

    from services.geometry import lookup_depth

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
                    sc = min(sa, float(og["score"][k]))
                    out.append((a, ia, int(og["i"][k]), sc, v, pts["X"][p], len(pts_obs[p])))
    return out


def candidate_links(
    views: list[ViewData],
    obs: dict[str, dict[str, np.ndarray]],
    aerial_cameras: dict[str, Camera],
    aerial_poses: dict[str, Pose],
    keypoints: dict[str, np.ndarray],
    conf: dict,
    aerial_features: dict[str, dict[str, np.ndarray]] | None,
    stats: dict[str, Any],
) -> Candidates:
    """The candidate aerial-ground matches per (aerial, ground) pair, each {ia, ig, score, view, X,
    n_aerial (the aerial images observing X)}:
    through the aerial points (3D) when aerial poses are known, else the paper's identity transfer.
    Counts go into stats (aerial_points, aerial_rejected, tracks, links)."""
    aerials = sorted(n for n in obs if image_set(n) == "aerial")
    grounds = sorted(n for n in obs if image_set(n) == "ground")
    cands: Candidates = {}
    if not stats["use_3d"]:  # no geometry: the paper's transfer on the keypoint tables alone
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
                            "n_aerial": 0,
                        }
                    )
        stats["links"] = int(sum(len(c) for c in cands.values()))
        return cands
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
    n_links = 0
    for g in grounds:
        for a, ia, ig, sc, v, X, n_aerial in _ground_links(views, pts, pts_obs, obs[g], conf):
            cand = {"ia": ia, "ig": ig, "score": sc, "view": v, "X": X, "n_aerial": n_aerial}
            cands.setdefault((a, g), []).append(cand)
            n_links += 1
    stats["links"] = n_links
    return cands


def _ground_links(
    views: list[ViewData],
    pts: dict[str, np.ndarray],
    pts_obs: list[list[tuple[str, int, float]]],
    og: dict[str, np.ndarray],
    conf: dict,
) -> list[tuple[str, int, int, float, int, np.ndarray, int]]:
    """link_points of one ground image's observations; with link.mode "identity" (the paper) only the
    points of the same render keypoint."""
    if conf["link"]["mode"] != "identity":
        return link_points(views, pts, pts_obs, og, conf)
    big = np.int64(1) << 32
    pkey = pts["view"] * big + pts["ir"]
    og = take(og, np.isin(og["view"] * big + og["ir"], pkey))
    same = np.isin(pkey, og["view"] * big + og["ir"])
    sub = {k: v[same] for k, v in pts.items()}
    sub_obs = [pts_obs[k] for k in np.flatnonzero(same)]
    return link_points(views, sub, sub_obs, og, merge_conf(conf, {"link": {"px": 1e-3}}))
