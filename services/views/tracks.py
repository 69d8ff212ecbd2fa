"""More of the scene than the sparse model holds: learned tracks across the aerial images, triangulated on
the aerial model's known poses.

The aerial SfM keeps what its features tie across the whole flight; the facades the oblique images see at
grazing angles hold few of its points, so the plane proxy (services.views.proxy) finds no plane for them.
Here every aerial image's most covisible partners (by shared sparse points) are matched again with ALIKED
keypoints at a higher resolution, guided by the epipolar geometry that the model's two poses give (each
keypoint's nearest descriptor among those near its epipolar line; or LightGlue, its matches then checked
against that line: no RANSAC, the geometry is known), and COLMAP's point triangulator
(`pycolmap.triangulate_points`, the model's poses and cameras held) builds tracks across all pairs,
merges and filters them by reprojection error and triangulation angle. The points seen by at least
min_track_length images, one per voxel_m voxel, go to the plane proxy beside the sparse points.

    points = TrackPoints.cached("sfm/sparse", "images", conf, "cache").points    # (N, 3) world points
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from services.colmap_model import Pose
from services.digests import sha256_file
from services.views.stereo import shared_points, voxel_means

logger = logging.getLogger("midview.views.tracks")

confs: dict[str, dict[str, Any]] = {
    "default": {
        # the aerial images' long side for ALIKED's keypoints (on isprs 1600 px: the same depth, 3x the time)
        "resize_max": 1024,
        "max_keypoints": 4096,
        "partners": 5,  # per image: the others that share the most sparse points with it
        "min_shared": 30,  # sparse points a pair must share
        # "epipolar" (guided: the mutual nearest descriptors among the keypoints near each other's epipolar
        # line, with a ratio test among those; no network) or "lightglue" (every keypoint against every
        # other, then the epipolar check): on isprs the same depth at the views, 10x the matching time
        "matcher": "epipolar",
        "filter_threshold": 0.1,  # LightGlue's match score threshold
        "ratio": 0.9,  # "epipolar": the nearest descriptor's distance over the second's, at most
        "max_epipolar_px": 2.0,  # a match's distance to its epipolar line (both images, at full size)
        "min_track_length": 3,  # images that must see a point
        "max_reproj_px": 2.0,  # the triangulator's filter
        "min_angle_deg": 2.0,  # the triangulator's smallest triangulation angle
        "voxel_m": 0.25,  # one point (the mean) per voxel
    },
}


def covisible_pairs(rec: pycolmap.Reconstruction, partners: int, min_shared: int) -> list[tuple[int, int]]:
    """(image id, image id) pairs, a < b: for every registered image its `partners` best partners by the
    sparse points they share (at least min_shared)."""
    shared = shared_points(rec)
    best: dict[int, list[tuple[int, int]]] = {}
    for (a, b), n in shared.items():
        if n >= min_shared:
            best.setdefault(a, []).append((n, b))
            best.setdefault(b, []).append((n, a))
    out = set()
    for a, cands in best.items():
        for _, b in sorted(cands, reverse=True)[:partners]:
            out.add((min(a, b), max(a, b)))
    return sorted(out)


def _normalized(cam: pycolmap.Camera, kp: np.ndarray) -> np.ndarray:
    """(N, 3) homogeneous normalized coordinates of pixel keypoints (N, 2), distortion removed."""
    return np.c_[cam.cam_from_img(np.asarray(kp, np.float64)), np.ones(len(kp))]


def _essential(pose0: Pose, pose1: Pose) -> np.ndarray:
    """E (3, 3) with x1^T E x0 = 0 for normalized points x0 of camera 0 and x1 of camera 1."""
    R = pose1.R @ pose0.R.T
    t = pose1.t - R @ pose0.t
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]]) @ R


def _line_distances(x0: np.ndarray, x1: np.ndarray, E: np.ndarray, f0: float, f1: float, pairwise: bool):
    """Pixel distances of x1 to the epipolar lines of x0 and of x0 to those of x1: (N,) each for matched
    rows, or (N0, N1) each with pairwise."""
    l1, l0 = x0 @ E.T, x1 @ E  # lines in image 1 of x0, in image 0 of x1
    r = np.abs(l1 @ x1.T) if pairwise else np.abs(np.sum(x1 * l1, axis=1))
    n1 = np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12)
    n0 = np.maximum(np.hypot(l0[:, 0], l0[:, 1]), 1e-12)
    if pairwise:
        return r / n0[None, :] * f0, r / n1[:, None] * f1
    return r / n0 * f0, r / n1 * f1


def epipolar_inliers(
    cam0: pycolmap.Camera,
    pose0: Pose,
    kp0: np.ndarray,
    cam1: pycolmap.Camera,
    pose1: Pose,
    kp1: np.ndarray,
    px: float,
) -> np.ndarray:
    """(M,) bool: the matched keypoints kp0[i] <-> kp1[i] (M, 2) within `px` pixels of each other's epipolar
    line, from the two known poses."""
    x0, x1 = _normalized(cam0, kp0), _normalized(cam1, kp1)
    f0, f1 = float(cam0.mean_focal_length()), float(cam1.mean_focal_length())
    d0, d1 = _line_distances(x0, x1, _essential(pose0, pose1), f0, f1, pairwise=False)
    return (d0 < px) & (d1 < px)


def epipolar_matches(
    cam0: pycolmap.Camera,
    pose0: Pose,
    feats0: dict,
    cam1: pycolmap.Camera,
    pose1: Pose,
    feats1: dict,
    px: float,
    ratio: float,
) -> np.ndarray:
    """(M, 2) guided matches: the mutual nearest descriptors (unit-norm) among the keypoint pairs within
    `px` pixels of each other's epipolar line, kept where the nearest is clearly nearer than the second
    nearest on the same line (distance ratio below `ratio`)."""
    x0, x1 = _normalized(cam0, feats0["keypoints"]), _normalized(cam1, feats1["keypoints"])
    f0, f1 = float(cam0.mean_focal_length()), float(cam1.mean_focal_length())
    d0, d1 = _line_distances(x0, x1, _essential(pose0, pose1), f0, f1, pairwise=True)
    sim = np.asarray(feats0["descriptors"], np.float32) @ np.asarray(feats1["descriptors"], np.float32).T
    sim[(d0 >= px) | (d1 >= px)] = -np.inf
    if not sim.size:
        return np.zeros((0, 2), np.int64)
    best1 = np.argmax(sim, axis=1)
    best0 = np.argmax(sim, axis=0)
    rows = np.arange(len(sim))
    top = sim[rows, best1]
    mutual = np.isfinite(top) & (best0[best1] == rows)
    second = np.partition(sim, -2, axis=1)[:, -2] if sim.shape[1] > 1 else np.full(len(sim), -np.inf)
    dist = lambda s: np.sqrt(np.maximum(2.0 - 2.0 * s, 0.0))  # noqa: E731 (unit descriptors)
    clear = dist(top) < ratio * dist(second)
    keep = mutual & clear
    return np.stack([rows[keep], best1[keep]], 1)


def _database(rec: pycolmap.Reconstruction, db_path: Path, keypoints: dict[int, np.ndarray]) -> None:
    """The model's cameras (same ids), one rig and frame per image, its images (same ids) and keypoints."""
    db = pycolmap.Database.open(str(db_path))
    try:
        rigs: dict[int, int] = {}
        for cid in sorted(rec.cameras):
            cam = rec.cameras[cid]
            new = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=cam.params)
            new.camera_id = cid
            db.write_camera(new, use_camera_id=True)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(new.sensor_id)
            rigs[cid] = db.write_rig(rig)
        for iid in sorted(keypoints):
            im = rec.images[iid]
            image = pycolmap.Image(name=im.name, camera_id=im.camera_id)
            image.image_id = iid
            db.write_image(image, use_image_id=True)
            frame = pycolmap.Frame(rig_id=rigs[im.camera_id])
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            db.write_keypoints(iid, np.ascontiguousarray(keypoints[iid], np.float32))
    finally:
        db.close()


def _match_pairs(
    rec: pycolmap.Reconstruction, db_path: Path, feats: dict[int, dict], pairs: list[tuple[int, int]], c: dict
) -> int:
    """Each pair matched (LightGlue or guided, conf "matcher"); its epipolar inliers written as its matches
    and geometry. -> their count."""
    from services.matching import match_features

    if c["matcher"] not in ("lightglue", "epipolar"):
        raise ValueError(f"unknown tracks matcher {c['matcher']!r} (lightglue, epipolar)")
    matcher = {"name": "lightglue", "features": "aliked", "filter_threshold": float(c["filter_threshold"])}
    px = float(c["max_epipolar_px"])
    poses = {i: Pose.of_image(rec.images[i]) for i in feats}
    db = pycolmap.Database.open(str(db_path))
    total = 0
    try:
        for a, b in pairs:
            ca, cb = rec.cameras[rec.images[a].camera_id], rec.cameras[rec.images[b].camera_id]
            if c["matcher"] == "epipolar":
                m = epipolar_matches(ca, poses[a], feats[a], cb, poses[b], feats[b], px, float(c["ratio"]))
            else:
                m, _ = match_features(feats[a], feats[b], matcher)
                kp_a, kp_b = feats[a]["keypoints"][m[:, 0]], feats[b]["keypoints"][m[:, 1]]
                m = m[epipolar_inliers(ca, poses[a], kp_a, cb, poses[b], kp_b, px)] if len(m) else m
            inl = np.ascontiguousarray(m, np.uint32).reshape(-1, 2)
            if len(inl) < 8:
                continue
            db.write_matches(a, b, inl)
            config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            db.write_two_view_geometry(a, b, pycolmap.TwoViewGeometry(config=config, inlier_matches=inl))
            total += len(inl)
    finally:
        db.close()
    return total


def triangulate(rec: pycolmap.Reconstruction, image_dir: str | Path, conf: dict | None = None) -> np.ndarray:
    """World points (N, 3) of the learned tracks (see the module's docstring), one per voxel."""
    from services.matching import extract, feature_confs
    from shared.images import read_image

    c = {**confs["default"], **(conf or {})}
    t0 = time.perf_counter()
    fconf = json.loads(json.dumps(feature_confs["aliked"]))
    fconf["model"]["max_num_keypoints"] = int(c["max_keypoints"])
    fconf["preprocessing"]["resize_max"] = int(c["resize_max"])
    pairs = covisible_pairs(rec, int(c["partners"]), int(c["min_shared"]))
    used = sorted({i for p in pairs for i in p})
    feats = {}
    for i in used:
        image = read_image(Path(image_dir) / rec.images[i].name)
        feats[i] = {**extract(fconf, image), "image_size": np.array(image.shape[1::-1], np.float32)}
    t_feat = time.perf_counter() - t0
    work = Path(tempfile.mkdtemp(prefix="midview-tracks-"))
    try:
        db_path = work / "tracks.db"
        _database(rec, db_path, {i: f["keypoints"] for i, f in feats.items()})
        n_matches = _match_pairs(rec, db_path, feats, pairs, c)
        t_match = time.perf_counter() - t0 - t_feat
        model = pycolmap.Reconstruction(rec)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.mapper.filter_max_reproj_error = float(c["max_reproj_px"])
        opts.mapper.filter_min_tri_angle = float(c["min_angle_deg"])
        opts.triangulation.min_angle = float(c["min_angle_deg"])
        (work / "out").mkdir()
        tri = pycolmap.triangulate_points(model, db_path, Path(image_dir), work / "out", options=opts)
        P = np.array(
            [p.xyz for p in tri.points3D.values() if p.track.length() >= int(c["min_track_length"])], float
        ).reshape(-1, 3)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = voxel_means(P, float(c["voxel_m"]))
    logger.info(
        "learned tracks: %d images, %d pairs, %d epipolar matches, %d points of >= %d images, %d voxels "
        "(features %.0f s, matching %.0f s, in all %.0f s)",
        len(used), len(pairs), n_matches, len(P), int(c["min_track_length"]), len(out),
        t_feat, t_match, time.perf_counter() - t0,
    )  # fmt: skip
    return out


def cached(
    model_dir: str | Path, image_dir: str | Path, conf: dict | None, cache_dir: str | Path | None
) -> np.ndarray:
    """The points of `triangulate`, read from cache_dir when computed there before from the same model (its
    images.bin and points3D.bin) and conf; else computed (and written there, an .npy)."""
    c = {**confs["default"], **(conf or {})}
    model_dir = Path(model_dir)
    if cache_dir is None:
        return triangulate(pycolmap.Reconstruction(str(model_dir)), image_dir, c)
    key = hashlib.sha256(json.dumps(c, sort_keys=True).encode())
    for f in ("images.bin", "points3D.bin"):
        key.update(sha256_file(model_dir / f).encode())
    path = Path(cache_dir) / f"tracks-{key.hexdigest()[:16]}.npy"
    if path.is_file():
        return np.load(path)
    P = triangulate(pycolmap.Reconstruction(str(model_dir)), image_dir, c)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, P)
    tmp.replace(path)
    return P
