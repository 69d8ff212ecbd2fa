"""The combined database: a copy of the aerial SfM database with the aerial images' keypoints extended by
the matching features the transferred matches refer to, the ground camera and images (their POS as pose
priors), the reducer's verified aerial-ground matches and the ground-ground pairs verified by an
essential matrix that agrees with the POS."""

from __future__ import annotations

import logging
import math
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose
from services.sfm.combined.surface import SurfaceCheck

logger = logging.getLogger("midview.combined_sfm")

PosStd = tuple[float, float, float]
Attitude = tuple[np.ndarray, float]  # a cam_from_world rotation (3, 3) and its std (degrees)


def copy_database(src: Path, dst: Path) -> Path:
    """Copy a COLMAP (SQLite) database consistently, write-ahead log included."""
    for p in (dst, dst.with_name(dst.name + "-wal"), dst.with_name(dst.name + "-shm")):
        p.unlink(missing_ok=True)
    dst.parent.mkdir(parents=True, exist_ok=True)
    s = sqlite3.connect(str(src))
    d = sqlite3.connect(str(dst))
    try:
        s.backup(d)
    finally:
        d.close()
        s.close()
    return dst


def _pad_like(kp: np.ndarray, cols: int) -> np.ndarray:
    """(N, 2) keypoints widened to the database's keypoint columns (identity shape, unit scale)."""
    kp = np.asarray(kp, np.float32).reshape(-1, 2)
    if cols <= 2:
        return kp
    if cols == 4:  # x, y, scale, orientation
        return np.concatenate([kp, np.ones((len(kp), 1), np.float32), np.zeros((len(kp), 1), np.float32)], 1)
    extra = np.tile(np.array([1, 0, 0, 1], np.float32), (len(kp), 1))  # affine a11 a12 a21 a22
    return np.concatenate([kp, extra], 1)[:, :cols]


def write_ground(db: pycolmap.Database, camera: Camera, names: list[str]) -> dict[str, int]:
    cam = camera.to_pycolmap(camera_id=0)
    cam.has_prior_focal_length = True
    cam.camera_id = db.write_camera(cam)
    rig = pycolmap.Rig()
    rig.add_ref_sensor(cam.sensor_id)
    rig_id = db.write_rig(rig)
    ids = {}
    for n in names:
        image = pycolmap.Image(name=n, camera_id=cam.camera_id)
        image.image_id = db.write_image(image)
        frame = pycolmap.Frame(rig_id=rig_id)
        frame.add_data_id(image.data_id)
        db.write_frame(frame)
        ids[n] = image.image_id
    return ids


def write_pair(
    db: pycolmap.Database,
    id0: int,
    id1: int,
    matches: np.ndarray,
    sizes: dict | None = None,
    calibrated: bool = False,
    cam2_from_cam1: dict | None = None,
) -> None:
    """Matches and their two-view geometry (all of them inliers); with `cam2_from_cam1` ({"R", "t"}, the
    essential matrix's relative pose) the geometry holds that pose and E, as COLMAP's matching stores
    them, for whatever reads the database next."""
    m = np.ascontiguousarray(np.asarray(matches, np.uint32).reshape(-1, 2))
    if db.exists_matches(id0, id1):
        return
    if sizes is not None:
        for i in (id0, id1):
            sizes[i] = max(sizes.get(i, 0), len(m))
    db.write_matches(id0, id1, m)
    tvg = pycolmap.TwoViewGeometry(
        config=pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        if calibrated
        else pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED,
        inlier_matches=m,
    )
    if cam2_from_cam1 is not None:
        R = np.asarray(cam2_from_cam1["R"], float)
        t = np.asarray(cam2_from_cam1["t"], float)
        tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        tvg.E = tx @ R
    db.write_two_view_geometry(id0, id1, tvg)


def ground_pairs(poses: dict[str, Pose], names: list[str], conf: dict) -> list[tuple[str, str]]:
    """Ground image pairs from the POS: nearest neighbours looking alike."""
    from services.geometry import angle_deg, optical_axis

    names = sorted(n for n in names if n in poses)
    out = set()
    for a in names:
        d = sorted((float(np.linalg.norm(poses[a].center - poses[b].center)), b) for b in names if b != a)
        k = 0
        for dist, b in d:
            if dist > conf["max_distance_m"] or k >= conf["num_neighbors"]:
                break
            if angle_deg(optical_axis(poses[a]), optical_axis(poses[b])) > conf["max_heading_deg"]:
                continue
            out.add(tuple(sorted((a, b))))
            k += 1
    return sorted(out)


def verify_ground_pair(
    kp0: np.ndarray,
    kp1: np.ndarray,
    matches: np.ndarray,
    camera: Camera,
    prior0: Pose,
    prior1: Pose,
    std0: tuple[float, float, float],
    std1: tuple[float, float, float],
    conf: dict,
    attitudes: tuple[Attitude | None, Attitude | None] = (None, None),
) -> tuple[np.ndarray, dict[str, Any]]:
    """The inlier matches (k, 2) of two ground images and a record of the check: an essential-matrix
    RANSAC (pycolmap, both images taken with `camera`), its relative pose compared with the POS poses
    (cam_from_world; std = (horizontal m, vertical m, attitude deg)), its rotation with the images'
    aerial-tied attitudes instead where both have one (`attitudes`: aerial_tied_attitudes). A
    fundamental matrix alone accepts repeated facade patterns between images that share nothing; the POS
    rejects them. Returns no inliers when the check fails."""
    from services.geometry import angle_deg, rotation_angle_deg

    none = np.zeros((0, 2), np.int64)
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    rec: dict[str, Any] = {"putative": len(m), "inliers": 0, "accepted": False}
    if len(m) < max(int(conf["min_inliers"]), 5):
        rec["reason"] = f"{len(m)} putative matches (< {conf['min_inliers']})"
        return none, rec
    o = pycolmap.TwoViewGeometryOptions()
    o.min_num_inliers = int(conf["min_inliers"])
    o.compute_relative_pose = True
    o.ransac.max_error = float(conf["ransac_px"])
    o.ransac.random_seed = int(conf["seed"])
    o.ransac.min_inlier_ratio = 0.1
    o.min_E_F_inlier_ratio = float(conf.get("min_e_f_inlier_ratio", o.min_E_F_inlier_ratio))
    cam = camera.to_pycolmap(1)
    p0 = np.ascontiguousarray(np.asarray(kp0, np.float64)[m[:, 0], :2])
    p1 = np.ascontiguousarray(np.asarray(kp1, np.float64)[m[:, 1], :2])
    idx = np.ascontiguousarray(np.stack([np.arange(len(m))] * 2, 1), np.uint32)
    tvg = pycolmap.estimate_calibrated_two_view_geometry(cam, p0, cam, p1, idx, o)
    inl = np.asarray(tvg.inlier_matches, np.int64).reshape(-1, 2)[:, 0]
    rec["inliers"] = len(inl)
    rec["config"] = pycolmap.TwoViewGeometryConfiguration(int(tvg.config)).name
    if len(inl) < int(conf["min_inliers"]):
        rec["reason"] = f"{len(inl)} inliers (< {conf['min_inliers']})"
        return none, rec
    uncalibrated = tvg.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
    if uncalibrated and conf.get("require_calibrated", True):
        rec["reason"] = (
            "an uncalibrated fundamental matrix explains more of its matches than any motion of the "
            "calibrated camera (repeated texture on different surfaces)"
        )
        return none, rec
    rel = tvg.cam2_from_cam1
    R_est = np.asarray(rel.rotation.matrix())
    R_pos = prior1.R @ prior0.R.T
    k = float(conf["prior_sigmas"])
    drot = rotation_angle_deg(R_est @ R_pos.T)
    lim_rot = max(k * math.sqrt(3.0 * (std0[2] ** 2 + std1[2] ** 2)), float(conf["min_rotation_deg"]))
    rec.update(rotation_deg=drot, rotation_limit_deg=lim_rot)
    reasons = []
    if drot > lim_rot:
        reasons.append(f"relative rotation {drot:.1f} deg from the POS (> {lim_rot:.1f})")
    if attitudes[0] is not None and attitudes[1] is not None:
        (R0, s0), (R1, s1) = attitudes
        d_tied = rotation_angle_deg(R_est @ (R1 @ R0.T).T)
        lim_tied = max(k * math.sqrt(s0**2 + s1**2), float(conf["min_tied_rotation_deg"]))
        rec.update(tied_rotation_deg=d_tied, tied_rotation_limit_deg=lim_tied)
        if d_tied > lim_tied:
            why = f"relative rotation {d_tied:.1f} deg from the images' aerial-tied attitudes"
            reasons.append(f"{why} (> {lim_tied:.1f})")
    t = np.asarray(rel.translation, float)
    base = prior1.center - prior0.center
    b = float(np.linalg.norm(base))
    noise = k * math.sqrt(2.0 * (std0[0] ** 2 + std1[0] ** 2) + std0[1] ** 2 + std1[1] ** 2)
    if np.linalg.norm(t) > 1e-9 and b > noise:
        # cam2_from_cam1 t = R1->2 (C1 - C2) in camera-2 coordinates: the baseline C2 - C1 is -R2^T t
        d_est = -prior1.R.T @ t
        ddir = angle_deg(d_est, base)
        lim_dir = math.degrees(math.asin(min(noise / b, 1.0))) + lim_rot
        lim_dir = max(lim_dir, float(conf["min_direction_deg"]))
        rec.update(direction_deg=ddir, direction_limit_deg=lim_dir)
        if ddir > lim_dir:
            reasons.append(f"baseline direction {ddir:.1f} deg from the POS (> {lim_dir:.1f})")
    if reasons:
        rec["reason"] = "; ".join(reasons)
        return none, rec
    rec.update(accepted=True, reason="ok", cam2_from_cam1={"R": R_est.tolist(), "t": t.tolist()})
    return m[inl], rec


@dataclass
class CombinedDatabase:
    """What the database step wrote and the later steps need: the database's path, image ids by name,
    the offset of each aerial image's matching features among its keypoints, the aerial-ground matches
    written [(aerial, ground, (M, 2) keypoint indices before the offset)], each image's largest pair,
    the ground images' POS and the ground-ground pairs' records."""

    path: Path
    ids: dict[str, int]
    offsets: dict[str, int]
    priors: dict[str, Pose]  # the ground images' POS poses in the aerial model's frame ...
    prior_std: dict[str, PosStd]  # ... and their standard deviations
    ag: list[tuple[str, str, np.ndarray]] = field(default_factory=list)
    pair_sizes: dict[int, int] = field(default_factory=dict)
    ground_pairs: dict[str, dict[str, Any]] = field(default_factory=dict)


def ground_features(
    names: list[str], feature_path: Path, image_dir: Path, match_conf: dict
) -> dict[str, dict[str, np.ndarray]]:
    """The matching features of the ground images, from the cache, extracted where it lacks them."""
    from services import matching

    out: dict[str, dict[str, np.ndarray] | None] = {}
    for n in names:
        try:
            out[n] = matching.load_features(feature_path, n)
        except (KeyError, OSError):
            out[n] = None
    missing = [n for n, f in out.items() if f is None]
    if missing:
        matching.extract_features(matching.view_feature_conf(match_conf), image_dir, missing, feature_path)
        for n in missing:
            out[n] = matching.load_features(feature_path, n)
    return out


def _extend_aerial(
    db: pycolmap.Database, ids: dict[str, int], t_kps: dict[str, np.ndarray]
) -> dict[str, int]:
    """Append the transferred matches' aerial keypoints to the aerial images' SfM keypoints; the offsets."""
    offsets: dict[str, int] = {}
    for n in sorted(t_kps):
        if not n.startswith("aerial/") or n not in ids:
            continue
        old = db.read_keypoints(ids[n])
        db.update_keypoints(
            ids[n], np.concatenate([old, _pad_like(t_kps[n], old.shape[1])]).astype(np.float32)
        )
        offsets[n] = len(old)
    return offsets


def _write_ground_images(
    db: pycolmap.Database,
    camera: Camera,
    g_feats: dict[str, dict[str, np.ndarray]],
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
) -> dict[str, int]:
    """The ground camera, images, keypoints and POS pose priors; their ids."""
    ids = write_ground(db, camera, sorted(g_feats))
    for n, f in sorted(g_feats.items()):
        db.write_keypoints(ids[n], np.ascontiguousarray(f["keypoints"], np.float32))
        if n in priors:
            sxy, sz, _ = prior_std[n]
            db.write_pose_prior(
                pycolmap.PosePrior(
                    corr_data_id=db.read_image(ids[n]).data_id,
                    position=priors[n].center,
                    position_covariance=np.diag([sxy**2, sxy**2, sz**2]),
                    coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                )
            )
    return ids


def _write_aerial_ground(
    db: pycolmap.Database, cdb: CombinedDatabase, t_pairs: list, t_kps: dict, g_feats: dict
) -> None:
    """The reducer's verified aerial-ground matches, the aerial side at its offset."""
    for pm in t_pairs:
        a, g = (pm.name0, pm.name1) if pm.name0.startswith("aerial/") else (pm.name1, pm.name0)
        m = pm.matches if pm.name0 == a else pm.matches[:, ::-1]
        inl = np.ones(len(m), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
        m = m[inl].astype(np.int64)
        if len(m) == 0 or a not in cdb.offsets or g not in cdb.ids:
            continue
        if len(g_feats[g]["keypoints"]) != len(t_kps[g]):
            raise ValueError(f"{g}: the feature cache and the transfer disagree on its keypoints")
        mm = np.stack([m[:, 0] + cdb.offsets[a], m[:, 1]], 1)
        write_pair(db, cdb.ids[a], cdb.ids[g], mm, cdb.pair_sizes)
        cdb.ag.append((a, g, m))


def surface_check(aerial_dir: Path, camera: Camera, conf: dict) -> SurfaceCheck | None:
    """The check of ground pairs against the aerial surface (conf["surface"]), None when it is off or the
    aerial model holds no plane to check against."""
    from services.views import PlaneProxy

    if not conf.get("surface", {}).get("enabled"):
        return None
    proxy = PlaneProxy.from_model(aerial_dir / "sparse")
    if not proxy.planes:
        logger.warning("ground pairs: the aerial model holds no plane; not checked against its surface")
        return None
    return SurfaceCheck(proxy, camera, conf["surface"])


def aerial_tied_poses(transfer_dir: Path) -> dict[str, tuple[Pose, PosStd]]:
    """The ground images' poses tied to the aerial images (the reducer's accepted PnP poses, in the aerial
    model's frame) with their standard deviations (position from the inliers, attitude 0.5 degrees)."""
    import json

    path = transfer_dir / "ground_poses.json"
    if not path.is_file():
        return {}
    out = {}
    for name, p in json.loads(path.read_text()).get("images", {}).items():
        if p.get("accepted") and p.get("R") is not None:
            sigma = float(p.get("position_std_m") or 0.25)
            out[name] = (Pose(np.asarray(p["R"], float), np.asarray(p["t"], float)), (sigma, sigma, 0.5))
    return out


def aerial_tied_attitudes(transfer_dir: Path, min_std_deg: float) -> dict[str, Attitude]:
    """The ground images' attitudes tied to the aerial images (the reducer's PnP poses with attitude_tied,
    accepted or not: a position the inliers leave uncertain can come with a sharp attitude), each with its
    standard deviation about its worst axis (degrees, at least min_std_deg)."""
    import json

    path = transfer_dir / "ground_poses.json"
    if not path.is_file():
        return {}
    return {
        name: (np.asarray(p["R"], float), max(float(p["attitude_std_deg"]), min_std_deg))
        for name, p in json.loads(path.read_text()).get("images", {}).items()
        if p.get("attitude_tied") and p.get("R") is not None and p.get("attitude_std_deg") is not None
    }


def _against_surface(
    surface: SurfaceCheck,
    anchors: dict[str, tuple[Pose, PosStd]] | None,
    g0: str,
    g1: str,
    f0: np.ndarray,
    f1: np.ndarray,
    inl: np.ndarray,
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
) -> dict[str, Any]:
    """The surface check of a verified pair, lifted from the image of the two that has an aerial-tied
    pose (`anchors`); not judged when neither has one."""
    p = [np.asarray(f, np.float64)[inl[:, i], :2] for i, f in enumerate((f0, f1))]
    names = [g0, g1]
    for a in (0, 1):
        if anchors and names[a] in anchors:
            pose, std = anchors[names[a]]
            b = 1 - a
            return surface(names[a], p[a], p[b], pose, priors[names[b]], std, prior_std[names[b]])
    return {"accepted": True, "reason": "neither image has a pose tied to the aerial images: not judged"}


def _write_ground_ground(
    db: pycolmap.Database,
    cdb: CombinedDatabase,
    g_feats: dict,
    camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
    match_conf: dict,
    conf: dict,
    prog,
    surface: SurfaceCheck | None = None,
    anchors: dict[str, tuple[Pose, PosStd]] | None = None,
    attitudes: dict[str, Attitude] | None = None,
    pair_cache: Path | None = None,
) -> int:
    """Ground pairs from the POS, matched (their matches kept in `pair_cache`, services.sfm.combined.
    pair_cache) and verified (verify_ground_pair, then against the aerial surface when `surface` is
    given); the number written."""
    from services.sfm.combined.pair_cache import match_ground_pairs

    gp = ground_pairs(priors, sorted(g_feats), conf)
    putative = match_ground_pairs(g_feats, gp, match_conf["matcher"], pair_cache, prog=prog)
    verified: dict[tuple[str, str], np.ndarray] = {}
    for g0, g1 in gp:
        mm = putative[(g0, g1)]
        f0, f1 = g_feats[g0]["keypoints"], g_feats[g1]["keypoints"]
        tied = ((attitudes or {}).get(g0), (attitudes or {}).get(g1))
        inl, rec = verify_ground_pair(
            f0, f1, mm, camera, priors[g0], priors[g1], prior_std[g0], prior_std[g1], conf, tied
        )
        if len(inl) and surface is not None:
            rec["surface"] = _against_surface(surface, anchors, g0, g1, f0, f1, inl, priors, prior_std)
            if not rec["surface"]["accepted"] and conf["surface"].get("enforce", True):
                rec.update(accepted=False, reason=f"against the aerial surface: {rec['surface']['reason']}")
                inl = inl[:0]
        cdb.ground_pairs[f"{g0} {g1}"] = rec
        if len(inl):
            verified[(g0, g1)] = inl
    args = (g_feats, camera, priors, prior_std, anchors, conf)
    refused = _against_each_other(cdb.ground_pairs, verified, *args)
    for pair, why in refused.items():
        cdb.ground_pairs[" ".join(pair)].update(accepted=False, reason=f"against the other pairs: {why}")
        verified.pop(pair)
    for (g0, g1), inl in verified.items():
        rel = cdb.ground_pairs[f"{g0} {g1}"].get("cam2_from_cam1")
        write_pair(db, cdb.ids[g0], cdb.ids[g1], inl, cdb.pair_sizes, True, rel)
    return len(verified)


def _against_each_other(
    records: dict[str, dict[str, Any]],
    verified: dict[tuple[str, str], np.ndarray],
    g_feats: dict,
    camera: Camera,
    priors: dict[str, Pose],
    prior_std: dict[str, PosStd],
    anchors: dict[str, tuple[Pose, PosStd]] | None,
    conf: dict,
) -> dict[tuple[str, str], str]:
    """The verified pairs whose baselines the others refuse (services.sfm.combined.consistency), each
    pair's direction turned into the model's frame by its first image's attitude (aerial-tied where the
    reducer has it, else the POS), and its length, where conf["depths"] is on, the one its matches' depths
    give it against the other pairs' (services.sfm.combined.depths)."""
    from services.sfm.combined.consistency import inconsistent_pairs, pair_direction
    from services.sfm.combined.depths import PairMatches, baseline_lengths

    cc = conf.get("consistency", {})
    if not cc.get("enabled", False):
        return {}
    dirs, matches = {}, {}
    for g0, g1 in verified:
        rel = records[f"{g0} {g1}"]["cam2_from_cam1"]
        R, t = np.asarray(rel["R"], float), np.asarray(rel["t"], float)
        first = (anchors or {}).get(g0, (priors[g0], None))[0]
        dirs[(g0, g1)] = pair_direction(R, t, first)
        inl = verified[(g0, g1)]
        kp0 = np.asarray(g_feats[g0]["keypoints"], float)[inl[:, 0], :2]
        kp1 = np.asarray(g_feats[g1]["keypoints"], float)[inl[:, 1], :2]
        matches[(g0, g1)] = PairMatches(kp0, kp1, R, t)
    sizes = {p: len(inl) for p, inl in verified.items()}
    pos = {(a, b): float(np.linalg.norm(priors[b].center - priors[a].center)) for a, b in verified}
    lengths = baseline_lengths(matches, pos, camera.K, conf.get("depths", {"enabled": False}))
    return inconsistent_pairs(dirs, priors, prior_std, cc, anchors, sizes, lengths)


def _ground_names(transfer_matches: Path) -> set[str]:
    """The ground images of the reducer's match file."""
    from shared.matchfile import MatchFile

    with MatchFile(transfer_matches, "r") as mf:
        return {n for n in mf.image_names() if n.startswith("ground/")}


def match_ground_pairs_ahead(
    aerial_dir: Path,
    image_dir: Path,
    feature_path: Path,
    pos: str | Path,
    match_conf: dict,
    conf: dict,
    cache: Path,
) -> int:
    """The ground-ground pairs build_database matches (the POS's neighbours), matched ahead of it into the
    pair cache `cache` from the features in `feature_path` (only read: a pair of an image it lacks is
    left to build_database). The demo's baselines' process does this beside the pipeline. Returns the
    number of pairs the cache holds for these features."""
    from services import matching
    from services.reduce import ground_priors
    from services.sfm.combined.pair_cache import match_ground_pairs

    priors, _ = ground_priors(pos, aerial_dir / "georef.json")
    feats = {}
    for n in sorted(n for n in priors if (image_dir / n).is_file()):
        try:
            feats[n] = matching.load_features(feature_path, n)
        except (KeyError, OSError):
            continue
    pairs = ground_pairs(priors, sorted(feats), conf["ground_pairs"])
    cache.parent.mkdir(parents=True, exist_ok=True)
    return len(match_ground_pairs(feats, pairs, match_conf["matcher"], cache))


def build_database(
    aerial_dir: Path,
    transfer_dir: Path,
    out_dir: Path,
    image_dir: Path,
    feature_path: Path,
    ground_camera: Camera,
    pos: str | Path,
    match_conf: dict,
    conf: dict,
    prog,
) -> CombinedDatabase:
    """out_dir/database.db (see the module docstring) from the aerial SfM's (aerial_dir), the reducer's
    matches (transfer_dir) and the ground images' matching features (cache feature_path, extracted from
    image_dir where it lacks them); the ground images are those of the reducer's matches and of the POS."""
    from services.reduce import ground_priors
    from services.sfm.combined.pair_cache import pair_cache_path
    from shared.matchfile import MatchFile

    priors, prior_std = ground_priors(pos, aerial_dir / "georef.json")
    names = sorted(
        n for n in _ground_names(transfer_dir / "matches.h5") | set(priors) if (image_dir / n).is_file()
    )
    g_feats = ground_features(names, feature_path, image_dir, match_conf)
    with MatchFile(transfer_dir / "matches.h5", "r") as mf:
        t_pairs = list(mf.iter_pairs())
        t_kps = {n: mf.keypoints(n) for n in mf.image_names()}
    path = copy_database(aerial_dir / "database.db", out_dir / "database.db")
    db = pycolmap.Database.open(str(path))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        cdb = CombinedDatabase(path, ids, _extend_aerial(db, ids, t_kps), priors, prior_std)
        ids.update(_write_ground_images(db, ground_camera, g_feats, priors, prior_std))
        _write_aerial_ground(db, cdb, t_pairs, t_kps, g_feats)
        args = (g_feats, ground_camera, priors, prior_std, match_conf, conf["ground_pairs"], prog)
        check = surface_check(aerial_dir, ground_camera, conf["ground_pairs"])
        tied = aerial_tied_attitudes(transfer_dir, float(conf["ground_pairs"]["tied_attitude_min_std_deg"]))
        cache = pair_cache_path(feature_path, match_conf["matcher"])
        n_gg = _write_ground_ground(db, cdb, *args, check, aerial_tied_poses(transfer_dir), tied, cache)
    finally:
        db.close()
    logger.info(
        "database: %d aerial-ground matches in %d pairs, %d/%d ground-ground pairs verified"
        " (essential matrix agreeing with the POS)",
        sum(len(m) for _, _, m in cdb.ag),
        len(cdb.ag),
        n_gg,
        len(cdb.ground_pairs),
    )
    return cdb
