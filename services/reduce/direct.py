"""The reducer's check applied to direct matches (a baseline): aerial keypoints lifted to 3D with the
aerial model's points, each ground image localized by PnP with its POS as a prior, the matches that
agree with the pose kept; written as the reducer writes its own, so that the combined SfM treats every
method alike."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.colmap_model import Camera, read_cameras_json
from services.conf import merge_conf
from services.geometry import pose_of_image
from services.reduce.confs import default_conf
from services.reduce.localize import estimate_ground_pose, ground_priors
from services.reduce.observations import image_set
from services.reduce.reducer import pose_document, write_match_file
from shared.matchfile import MatchFile


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
    kps = np.asarray(kps, float).reshape(-1, 2)
    d, j = tree.query(kps, k=k, distance_upper_bound=radius_px)
    d, j = d.reshape(len(kps), k), j.reshape(len(kps), k)
    zz = np.where(np.isfinite(d), np.append(zs, np.nan)[j], np.nan)  # (N, k): a miss indexes len(zs)
    found = np.isfinite(zz).sum(1) >= 3
    with np.errstate(invalid="ignore"):
        found[found] &= np.nanmax(zz[found], 1) / np.nanmin(zz[found], 1) <= max_ratio
    if found.any():
        out[found] = pose.unproject(K, kps[found], np.nanmedian(zz[found], 1))
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
    so that the combined SfM can reconstruct with them (the same procedure for every method)."""
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
        est = estimate_ground_pose(kp[ok], X[ok], cams["ground"], priors.get(g), prior_std.get(g), conf)
        poses[g] = est.to_dict()
        for a, m, sc, x in items:
            keep = np.zeros(len(m), bool)
            if est.verifies(conf["pnp"]):
                good = np.isfinite(x).all(1)
                uv, z = est.pose.project(cams["ground"].K, np.where(good[:, None], x, 0.0))
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
