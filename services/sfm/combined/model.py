"""The combined SfM's input model: the aerial model with extended keypoints, the ground images held at an
accepted PnP pose (seed_pnp_poses) and one 3D point per transferred track, from which pycolmap's
incremental mapper continues."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

logger = logging.getLogger("midview.combined_sfm")


def _read_database(db_path: Path) -> tuple[dict, dict, dict[int, np.ndarray]]:
    """(images by id, cameras by id, keypoints (N, 2) by image id) of a COLMAP database."""
    db = pycolmap.Database.open(str(db_path))
    try:
        db_images = {im.image_id: im for im in db.read_all_images()}
        db_cams = {c.camera_id: c for c in db.read_all_cameras()}
        kps = {i: db.read_keypoints(i)[:, :2].astype(np.float64) for i in db_images}
    finally:
        db.close()
    return db_images, db_cams, kps


def _add_aerial(
    rec: pycolmap.Reconstruction,
    aerial: pycolmap.Reconstruction,
    db_cams: dict,
    ids: dict[str, int],
    kps: dict[int, np.ndarray],
) -> set[str]:
    """The database's cameras (the aerial model's intrinsics where it refined them) and the aerial
    model's registered images with the extended keypoints; their names."""
    for cam_id in sorted(db_cams):
        rec.add_camera_with_trivial_rig(db_cams[cam_id])
    for cam_id, cam in aerial.cameras.items():
        if cam_id in db_cams:
            rec.cameras[cam_id].params = cam.params
    registered: set[str] = set()
    for name, img in sorted((im.name, im) for im in aerial.images.values() if im.has_pose):
        iid = ids[name]
        if iid != img.image_id:
            raise RuntimeError(f"{name}: image id {img.image_id} in the aerial model, {iid} in its database")
        im = pycolmap.Image(name=name, keypoints=kps[iid], camera_id=img.camera_id, image_id=iid)
        rec.add_image_with_trivial_frame(im, img.cam_from_world())
        registered.add(name)
    return registered


def pose_of_record(r: dict) -> pycolmap.Rigid3d:
    """The cam_from_world pose of a reducer's ground_poses.json record (R, t)."""
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(r["R"], float)), np.asarray(r["t"], float))


def _add_pnp_seeds(
    rec: pycolmap.Reconstruction,
    pnp: dict[str, dict],
    ids: dict[str, int],
    kps: dict[int, np.ndarray],
    ground_cam_id: int | None,
    pair_sizes: dict[int, int],
    conf: dict,
) -> set[str]:
    """The ground images held at their accepted PnP pose (seed_pnp_poses; with "trusted" only poses that
    rest on trusted rendered depth) that have a pair the mapper keeps; their names."""
    out: set[str] = set()
    if not conf["seed_pnp_poses"]:
        return out
    min_pair = max(int(conf["mapping"]["min_num_matches"]), int(conf["min_seed_matches"]))
    for g, r in sorted(pnp.items()):
        # the mapper only keeps images with a pair of at least min_num_matches correspondences
        if not r.get("accepted") or g not in ids or pair_sizes.get(ids[g], 0) < min_pair:
            continue
        if conf["seed_pnp_poses"] == "trusted" and not rests_on_trusted_depth(r, conf):
            continue
        iid = ids[g]
        im = pycolmap.Image(name=g, keypoints=kps[iid], camera_id=ground_cam_id, image_id=iid)
        pose = pose_of_record(r)
        rec.add_image_with_trivial_frame(im, pose)
        out.add(g)
    return out


def build_input_model(
    aerial: pycolmap.Reconstruction,
    db_path: Path,
    ids: dict[str, int],
    offsets: dict[str, int],
    ag: list[tuple[str, str, np.ndarray]],
    pnp: dict[str, dict],
    pair_sizes: dict[int, int],
    conf: dict,
    out: Path,
) -> pycolmap.Reconstruction:
    """The aerial model with extended keypoints, the PnP-registered ground images and the transferred
    tracks (see services.sfm.combined); written to `out`."""
    db_images, db_cams, kps = _read_database(db_path)
    rec = pycolmap.Reconstruction()
    registered = _add_aerial(rec, aerial, db_cams, ids, kps)
    ground_cam_id = next((db_images[ids[n]].camera_id for n in ids if n.startswith("ground/")), None)
    registered |= _add_pnp_seeds(rec, pnp, ids, kps, ground_cam_id, pair_sizes, conf)
    # every other database image, unregistered (the mapper expects a frame for each)
    for iid, dbim in sorted(db_images.items()):
        if dbim.name in registered:
            continue
        im = pycolmap.Image(name=dbim.name, keypoints=kps[iid], camera_id=dbim.camera_id, image_id=iid)
        rec.add_image_with_trivial_frame(im)
    for _, p in sorted(aerial.points3D.items()):
        rec.add_point3D(p.xyz, pycolmap.Track(p.track.elements), p.color)
    n_seed = seed_tracks(rec, ids, offsets, ag, kps, registered) if conf["seed_points"] else 0
    out.mkdir(parents=True, exist_ok=True)
    rec.write(str(out))
    logger.info(
        "input model: %d aerial + %d ground images registered, %d aerial points, %d seeded tracks",
        sum(n.startswith("aerial/") for n in registered),
        sum(n.startswith("ground/") for n in registered),
        aerial.num_points3D(),
        n_seed,
    )
    return rec


def rests_on_trusted_depth(pose: dict, conf: dict) -> bool:
    """Whether a reducer's PnP pose (ground_poses.json) rests on rendered depth it trusted: at least
    seed_min_trusted_ratio of its inliers (and one) lifted by such depth."""
    n = int(pose.get("num_inliers", 0))
    return n > 0 and int(pose.get("trusted_depth_inliers", 0)) >= conf["seed_min_trusted_ratio"] * n


def registered_ground(rec: pycolmap.Reconstruction) -> set[str]:
    """Names of the ground images `rec` holds a pose for."""
    return {im.name for im in rec.images.values() if im.has_pose and im.name.startswith("ground/")}


def seed_tracks(
    rec: pycolmap.Reconstruction,
    ids: dict[str, int],
    offsets: dict[str, int],
    ag: list[tuple[str, str, np.ndarray]],
    kps: dict[int, np.ndarray],
    registered: set[str],
) -> int:
    """One 3D point per connected set of transferred observations, placed by a linear triangulation of
    its observations in registered images (at least two) and observed by those. The transferred matches
    of a ground image not registered yet link its keypoint to the aerial keypoints of one point: they
    join the point's aerial observations (the reducer's track) without being part of its track, so
    that the mapper sees that image's correspondences to the point and can register it."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    reg_ids = {ids[n] for n in registered if n in ids}
    for a, g, m in ag:
        if a not in registered:
            continue
        for ia, ig in m:
            u, v = (ids[a], int(ia) + offsets[a]), (ids[g], int(ig))
            ru, rv = find(u), find(v)
            if ru != rv:
                parent[max(ru, rv)] = min(ru, rv)
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for x in list(parent):
        groups.setdefault(find(x), []).append(x)
    n = 0
    for root in sorted(groups):
        members = sorted(groups[root])
        if len({i for i, _ in members}) != len(members):
            continue  # two keypoints of one image in a track: inconsistent, skip it
        obs = [(i, k) for i, k in members if i in reg_ids]
        if len(obs) < 2 or not any(rec.images[i].name.startswith("aerial/") for i, _ in obs):
            continue
        X = triangulate(rec, obs, kps)
        if X is None:
            continue
        track = pycolmap.Track([pycolmap.TrackElement(i, k) for i, k in obs])
        rec.add_point3D(X, track, np.array([128, 128, 128], np.uint8))
        n += 1
    return n


def triangulate(
    rec: pycolmap.Reconstruction,
    obs: list[tuple[int, int]],
    kps: dict[int, np.ndarray],
    max_px: float = 8.0,
) -> np.ndarray | None:
    """Linear (DLT) triangulation; None when it lies behind a camera or reprojects badly (> max_px)."""
    A = []
    Ps = []
    for iid, k in obs:
        img = rec.images[iid]
        P = projection(img)
        x, y = kps[iid][k]
        A.append(x * P[2] - P[0])
        A.append(y * P[2] - P[1])
        Ps.append((P, kps[iid][k]))
    _, _, Vt = np.linalg.svd(np.asarray(A))
    Xh = Vt[-1]
    if abs(Xh[3]) < 1e-12:
        return None
    X = Xh[:3] / Xh[3]
    for P, uv in Ps:
        p = P @ np.append(X, 1.0)
        if p[2] <= 0 or np.linalg.norm(p[:2] / p[2] - uv) > max_px:
            return None
    return X


def projection(image: pycolmap.Image) -> np.ndarray:
    """The 3x4 projection matrix K [R | t] of a posed image (pinhole part of its camera)."""
    return np.asarray(image.camera.calibration_matrix()) @ np.asarray(image.cam_from_world().matrix())


def max_angle_deg(rec: pycolmap.Reconstruction, X: np.ndarray, image_ids: list[int]) -> float:
    """The largest angle (degrees) at X between the rays of the images `image_ids`."""
    d = np.array([np.asarray(rec.images[i].projection_center()) - X for i in image_ids])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((d @ d.T).min(), -1.0, 1.0))))
