"""The reducer's entry points: `reduce_views` on loaded views (named steps: keypoints, observations,
candidate links, merge, localization, pairwise check) and `main` over the job's files."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose, read_cameras_json, read_model
from services.conf import merge_conf
from services.reduce.confs import default_conf
from services.reduce.localize import PosStd, ground_priors, localize_grounds
from services.reduce.merge import merge_candidates, verify_pairs
from services.reduce.observations import (
    ViewData,
    collect_keypoints,
    image_set,
    load_aerial_features,
    load_views,
    observations,
)
from services.reduce.points import candidate_links
from shared.logging import stage
from shared.matchfile import MatchFile, PairMatches

logger = logging.getLogger("midview.reduce")


def reduce_views(
    views: list[ViewData],
    aerial_cameras: dict[str, Camera],
    aerial_poses: dict[str, Pose],
    ground_camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
    conf: dict | None = None,
    aerial_features: dict[str, dict[str, np.ndarray]] | None = None,
) -> tuple[dict[tuple[str, str], dict], dict[str, np.ndarray], dict[str, dict], dict]:
    """The reducer on loaded views. Returns (pairs, keypoints, ground poses, stats); pairs maps
    (aerial, ground) to arrays matches (M, 2), scores, inliers, views (index into stats["views"]) and X
    (the 3D point of each match, NaN without 3D); a ground pose is PoseEstimate.to_dict().
    `aerial_features` (image name -> keypoints and descriptors of the matching features) lets the aerial
    points be completed over all those images."""
    conf = merge_conf(default_conf, conf)
    views = sorted(views, key=lambda v: v.name)
    view_names = [v.name for v in views]
    if len(set(view_names)) != len(view_names):
        raise ValueError("view names must be unique")
    keypoints = collect_keypoints(views, aerial_features)
    obs = observations(views, conf)
    use_3d = bool(conf["pnp"]["enabled"]) and any(a in aerial_poses for a in obs if image_set(a) == "aerial")
    stats: dict[str, Any] = {"views": view_names, "use_3d": use_3d}
    cands = candidate_links(views, obs, aerial_cameras, aerial_poses, keypoints, conf, aerial_features, stats)
    merged = merge_candidates(cands, view_names)
    poses: dict[str, dict] = {}
    verified = {k: np.ones(len(m["ia"]), bool) for k, m in merged.items()}
    if use_3d:
        depth_error = stats["aerial_rejected"]["depth_error"]
        centres = np.array([v.pose.center for v in views], float).reshape(-1, 3)
        estimates, verified = localize_grounds(
            merged, obs, keypoints, ground_camera, priors, prior_std, depth_error, view_names, conf, centres
        )
        poses = {g: est.to_dict() for g, est in estimates.items()}
    pairs = verify_pairs(merged, verified, keypoints, conf)
    del stats["use_3d"]
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
        from services.sfm import read_georef_frame

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


def view_cover(doc: dict) -> dict[str, dict]:
    """Per ground image of the views (views/views.json `doc`): how many views it is a candidate of and the
    largest share of such a view that its renderer coloured from the aerial images (the render's
    `source_fraction`; 1.0 where the renderer does not say): what the aerial images can show of it."""
    out: dict[str, dict] = {}
    for v in doc.get("views", []):
        frac = float(v.get("render", {}).get("source_fraction", 1.0))
        for g in v.get("ground", []):
            d = out.setdefault(g, {"views": 0, "view_aerial_fraction": 0.0})
            d["views"] += 1
            d["view_aerial_fraction"] = max(d["view_aerial_fraction"], round(frac, 4))
    return out


def reduce_report(stats: dict, pairs: dict, poses: dict[str, dict], conf: dict, seconds: float) -> dict:
    """report.json: the counts, each ground pose's verdict, each pair's putative and verified matches."""
    keys = (
        "accepted",
        "reason",
        "num_correspondences",
        "num_inliers",
        "to_pos",
        "views",
        "view_aerial_fraction",
    )
    return {
        **{k: v for k, v in stats.items() if k != "views"},
        "num_views": len(stats["views"]),
        "ground_poses": {g: {k: r.get(k) for k in keys} for g, r in sorted(poses.items())},
        "pairs": {
            f"{a} {g}": {"putative": int(len(p["matches"])), "verified": int(p["inliers"].sum())}
            for (a, g), p in sorted(pairs.items())
        },
        "seconds": seconds,
        "conf": conf,
    }


def main(
    conf: dict | None,
    views_json: str | Path,
    match_files: Sequence[str | Path],
    sparse: str | Path,
    pos: str | Path,
    cameras: str | Path | dict[str, Camera],
    georef: str | Path,
    out_dir: str | Path,
    database: bool = True,
    features: str | Path | None = None,
) -> Path:
    """Run the reducer; returns out_dir/matches.h5 (see services.reduce for the other outputs).
    `features`: the matching features' cache (services.matching.features), for the aerial track completion."""
    conf = merge_conf(default_conf, conf)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with stage("reduce", logger):
        t0 = time.perf_counter()
        views, doc = load_views(views_json, sorted(Path(p) for p in match_files))
        cams = read_cameras_json(cameras) if isinstance(cameras, str | Path) else dict(cameras)
        a_cams, a_poses = read_model(sparse)
        priors, prior_std = ground_priors(pos, georef)
        a_feats = load_aerial_features(features, sorted(a_poses)) if features is not None else None
        pairs, keypoints, poses, stats = reduce_views(
            views, a_cams, a_poses, cams["ground"], priors, prior_std, conf, a_feats
        )
        for g in priors:  # every ground image, also those no view gave a correspondence
            poses.setdefault(g, {"accepted": False, "num_correspondences": 0, "reason": "no correspondences"})
            poses[g].update(view_cover(doc).get(g, {"views": 0, "view_aerial_fraction": 0.0}))
        sizes = {n: (cams[s].width, cams[s].height) for n in keypoints if (s := image_set(n)) in cams}
        match_path = write_match_file(out_dir / "matches.h5", pairs, keypoints, sizes, stats["views"])
        (out_dir / "ground_poses.json").write_text(json.dumps(pose_document(poses, georef), indent=1))
        if database:
            from services.colmap_db import export_to_database

            export_to_database(match_path, out_dir / "database.db", cams, only_inliers=True)
        report = reduce_report(stats, pairs, poses, conf, time.perf_counter() - t0)
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
