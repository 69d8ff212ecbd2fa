"""Combined aerial + ground reconstruction, seeded with the aerial model.

Database (out/database.db), a copy of the aerial SfM database with:
- the aerial images' keypoints extended: the aerial SfM keypoints first (their indices, matches and
  the aerial model's tracks stay valid), then the matching features (services.features cache) the
  transferred matches refer to, at an offset;
- the ground camera, the ground images with their matching features and their POS as pose priors;
- ground-ground matches (POS neighbours, the matching features, an essential-matrix RANSAC whose
  relative pose must agree with the POS: facades repeat, and a fundamental matrix alone verified pairs
  that share nothing) and the transferred aerial-ground matches (the reducer's verified matches), with
  two-view geometries.

Input model (out/input): the aerial model rebuilt with the extended keypoints (with `seed_pnp_poses`
also the ground images whose PnP pose the reducer accepted, held at that pose: by default those whose
pose rests on rendered depth the reducer trusted), and one 3D point per
transferred track, triangulated from its observations in registered images; the keypoints of the other
ground images link a track's aerial observations without being part of it. pycolmap's incremental mapper
continues from it (`input_path`): it registers the other ground images through these points,
triangulates, and bundle-adjusts everything; ground images it registered but the model leaves uncertain
(their own points do not count for more than the aerial points that place them) or far from their POS
are dropped, and those the reducer localized are added at their PnP pose where the mapper left them out.
The result is georeferenced like the aerial model (a similarity to the aerial POS in the aerial model's
ENU frame) and written to out/sparse with report.json (NRI per set, N3P, reprojection error, ground
camera positions against the PnP and POS).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose, read_cameras_json
from services.conf import merge_conf
from services.geometry import pose_of_image
from services.pos import DEFAULT_STD_XY
from shared.logging import stage

logger = logging.getLogger("midview.combined_sfm")

default_conf: dict[str, Any] = {
    "ground_pairs": {
        "num_neighbors": 4,  # each ground image with its nearest ground images (POS) ...
        "max_distance_m": 40.0,  # ... within this distance ...
        "max_heading_deg": 100.0,  # ... whose viewing directions differ by less than this
        "min_inliers": 15,
        # verification: an essential matrix (both cameras calibrated) whose relative pose agrees with
        # the POS: rotation within prior_sigmas x the attitude noise (at least min_rotation_deg), the
        # baseline's direction within the angle the position noise allows (unchecked when the noise
        # is as large as the baseline)
        "ransac_px": 3.0,
        "prior_sigmas": 3.0,
        "min_rotation_deg": 10.0,
        "min_direction_deg": 15.0,
        "seed": 0,
    },
    "seed_points": True,  # 3D points of the transferred tracks in the input model
    # ground images with an accepted PnP pose start registered, held at that pose ... (off: the mapper
    # registers them like the others and they are judged like the others; those it leaves out or drops
    # are added at their PnP pose, see add_pnp_images. A PnP pose on points triangulated through a
    # CPU-trained 3DGS's blurry renders can be 0.8 m off within its 0.25 m std, and held fixed it drags
    # the chain of ground images the mapper registers from it: small-walk, README). "trusted": only the
    # poses that rest on rendered depth the reducer trusted (at least seed_min_trusted_ratio of their
    # inliers lifted by the depth of views whose depth agrees with the aerial points: exact renders)
    "seed_pnp_poses": "trusted",
    "seed_min_trusted_ratio": 0.5,
    "min_seed_matches": 15,  # ... when one of their pairs has this many matches (and min_num_matches)
    # ground images with an accepted PnP pose that the mapper could not keep (their 2D-3D support comes
    # from many aerial images, or from the rendered depth, with no pair of min_num_matches) are added
    # to the combined model at that pose, observing the model's points their transferred matches reach
    "add_pnp_images": True,
    "add_max_px": 4.0,  # such an observation must reproject within this (ground pixels)
    "add_min_angle_deg": 2.0,  # a new aerial-ground point must be seen under this angle at least
    # ground images the mapper registered itself (not at an accepted PnP pose) are dropped when the
    # model leaves their camera centre this uncertain (standard deviation along the worst direction from
    # the bundle adjustment's covariance, pixel noise at least 1 px: services.pose_uncertainty.
    # joint_position_stds; None: kept), or when their pose disagrees with their POS (the reducer's limits)
    "max_position_std_m": 0.5,
    "pos_limits": None,  # those POS limits: the reducer's conf["pnp"] (None: services.reduce's defaults)
    "mapping": {
        "min_num_matches": 15,  # pairs with fewer matches are ignored by the mapper
        "abs_pose_min_num_inliers": 15,
        "abs_pose_min_inlier_ratio": 0.15,
        "abs_pose_max_error": 8.0,
        "min_model_size": 3,
        "refine_intrinsics": False,
        "fix_aerial": True,  # the input model (aerial + PnP-seeded ground) stays fixed; BA refines the rest
        "seed": 0,
    },
    "georef": True,
    # GeoPackage/GeoJSON cameras, omega/phi/kappa text and LAS points in out_dir/gis (services.sfm.gis)
    "gis": True,
    "colmap_log_level": 1,
}


# -- database ------------------------------------------------------------------------------------
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


def _write_ground(db: pycolmap.Database, camera: Camera, names: list[str]) -> dict[str, int]:
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


def _write_pair(
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
    from services.viewpoints import angle_deg, optical_axis

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
) -> tuple[np.ndarray, dict[str, Any]]:
    """The inlier matches (k, 2) of two ground images and a record of the check: an essential-matrix
    RANSAC (pycolmap, both images taken with `camera`), its relative pose compared with the POS poses
    (cam_from_world; std = (horizontal m, vertical m, attitude deg)). A fundamental matrix alone
    accepts repeated facade patterns between images that share nothing; the POS rejects them.
    Returns no inliers when the check fails."""
    from services.geometry import rotation_angle_deg
    from services.viewpoints import angle_deg

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


# -- main ----------------------------------------------------------------------------------------
def main(
    conf: dict | None,
    aerial_dir: str | Path,
    transfer_dir: str | Path,
    feature_path: str | Path,
    match_conf: dict,
    image_dir: str | Path,
    pos: str | Path,
    cameras: str | Path | dict[str, Camera],
    out_dir: str | Path,
    progress=None,
) -> Path:
    """Build the combined database and model; returns out_dir/sparse. `aerial_dir` is the aerial SfM
    output (database.db, sparse/, georef.json), `transfer_dir` the reducer's (matches.h5,
    ground_poses.json), `feature_path` the matching features' cache and `match_conf` the matching conf
    (services.matching.views) for the ground-ground pairs."""
    from services import features as features_mod
    from services.matching import direct
    from services.pos import read_pos
    from services.reduce import default_conf as transfer_default_conf
    from services.reduce import ground_priors
    from services.sfm import georef as georef_mod
    from services.sfm.aerial import colmap_log_level
    from services.sfm.georef import read_georef_frame
    from shared.matchfile import MatchFile

    conf = merge_conf(default_conf, conf)
    aerial_dir, transfer_dir, out_dir = Path(aerial_dir), Path(transfer_dir), Path(out_dir)
    image_dir = Path(image_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cams = read_cameras_json(cameras) if isinstance(cameras, str | Path) else dict(cameras)
    prog = progress or (lambda f, m: None)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}

    with stage("combined:database", logger):
        t0 = time.perf_counter()
        db_path = copy_database(aerial_dir / "database.db", out_dir / "database.db")
        priors, prior_std = ground_priors(pos, aerial_dir / "georef.json")
        with MatchFile(transfer_dir / "matches.h5", "r") as mf:
            t_names = mf.image_names()
            t_pairs = [pm for pm in mf.iter_pairs()]
            t_kps = {n: mf.keypoints(n) for n in t_names}
        feature_path = Path(feature_path)
        ground_names = sorted(set(n for n in t_names if n.startswith("ground/")) | set(priors))
        ground_names = [n for n in ground_names if (image_dir / n).is_file()]
        g_feats: dict[str, dict] = {}
        for n in ground_names:
            try:
                g_feats[n] = features_mod.load_features(feature_path, n)
            except (KeyError, OSError):
                g_feats[n] = None
        missing = [n for n, f in g_feats.items() if f is None]
        if missing:
            from services.matching.views import feature_conf

            features_mod.main(feature_conf(match_conf), image_dir, missing, feature_path)
            for n in missing:
                g_feats[n] = features_mod.load_features(feature_path, n)
        db = pycolmap.Database.open(str(db_path))
        try:
            ids = {im.name: im.image_id for im in db.read_all_images()}
            offsets: dict[str, int] = {}
            for n in sorted(t_names):
                if not n.startswith("aerial/") or n not in ids:
                    continue
                old = db.read_keypoints(ids[n])
                new = np.concatenate([old, _pad_like(t_kps[n], old.shape[1])]).astype(np.float32)
                db.update_keypoints(ids[n], new)
                offsets[n] = len(old)
            g_ids = _write_ground(db, cams["ground"], ground_names)
            ids.update(g_ids)
            for n in ground_names:
                db.write_keypoints(ids[n], np.ascontiguousarray(g_feats[n]["keypoints"], np.float32))
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
            # transferred aerial-ground matches (verified only)
            pair_sizes: dict[int, int] = {}  # image id -> its largest pair in the database
            n_ag = 0
            ag: list[tuple[str, str, np.ndarray]] = []
            for pm in t_pairs:
                a, g = (pm.name0, pm.name1) if pm.name0.startswith("aerial/") else (pm.name1, pm.name0)
                m = pm.matches if pm.name0 == a else pm.matches[:, ::-1]
                inl = np.ones(len(m), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
                m = m[inl].astype(np.int64)
                if len(m) == 0 or a not in offsets or g not in ids:
                    continue
                if len(g_feats[g]["keypoints"]) != len(t_kps[g]):
                    raise ValueError(f"{g}: the feature cache and the transfer disagree on its keypoints")
                mm = np.stack([m[:, 0] + offsets[a], m[:, 1]], 1)
                _write_pair(db, ids[a], ids[g], mm, pair_sizes)
                ag.append((a, g, m))
                n_ag += len(m)
            # ground-ground
            gp = ground_pairs(priors, ground_names, conf["ground_pairs"])
            n_gg = 0
            gg_records = {}
            for i, (g0, g1) in enumerate(gp):
                mm, _ = direct.match_features(g_feats[g0], g_feats[g1], match_conf["matcher"])
                inl, rec_gg = verify_ground_pair(
                    g_feats[g0]["keypoints"],
                    g_feats[g1]["keypoints"],
                    mm,
                    cams["ground"],
                    priors[g0],
                    priors[g1],
                    prior_std[g0],
                    prior_std[g1],
                    conf["ground_pairs"],
                )
                gg_records[f"{g0} {g1}"] = rec_gg
                if len(inl):
                    _write_pair(db, ids[g0], ids[g1], inl, pair_sizes, True, rec_gg.get("cam2_from_cam1"))
                    n_gg += 1
                prog(0.6 * (i + 1) / max(len(gp), 1), f"ground pair {i + 1}/{len(gp)}")
        finally:
            db.close()
        timings["database"] = time.perf_counter() - t0
        logger.info(
            "database: %d aerial-ground matches in %d pairs, %d/%d ground-ground pairs verified"
            " (essential matrix agreeing with the POS)",
            n_ag,
            len(ag),
            n_gg,
            len(gp),
        )

    with stage("combined:input-model", logger):
        aerial = pycolmap.Reconstruction(str(aerial_dir / "sparse"))
        pnp = json.loads((transfer_dir / "ground_poses.json").read_text())["images"]
        seed = build_input_model(aerial, db_path, ids, offsets, ag, pnp, pair_sizes, conf, out_dir / "input")

    with stage("combined:mapping", logger):
        t0 = time.perf_counter()
        mc = conf["mapping"]
        o = pycolmap.IncrementalPipelineOptions()
        o.random_seed = int(mc["seed"])
        o.mapper.random_seed = int(mc["seed"])
        o.min_model_size = int(mc["min_model_size"])
        o.min_num_matches = int(mc["min_num_matches"])
        o.multiple_models = False
        o.use_prior_position = False
        o.fix_existing_frames = bool(mc["fix_aerial"])
        o.mapper.abs_pose_min_num_inliers = int(mc["abs_pose_min_num_inliers"])
        o.mapper.abs_pose_min_inlier_ratio = float(mc["abs_pose_min_inlier_ratio"])
        o.mapper.abs_pose_max_error = float(mc["abs_pose_max_error"])
        refine = bool(mc["refine_intrinsics"])
        o.ba_refine_focal_length = refine
        o.ba_refine_extra_params = refine
        o.ba_refine_principal_point = False
        o.mapper.abs_pose_refine_focal_length = refine
        o.mapper.abs_pose_refine_extra_params = refine
        models_dir = out_dir / "models"
        if models_dir.exists():
            shutil.rmtree(models_dir)
        models_dir.mkdir(parents=True)
        n_total = len(ids)
        state = {"n": seed.num_reg_images()}

        def registered() -> None:
            state["n"] += 1
            prog(0.6 + 0.35 * min(state["n"] / max(n_total, 1), 1.0), f"{state['n']} images registered")

        with colmap_log_level(conf["colmap_log_level"]):
            models = pycolmap.incremental_mapping(
                db_path,
                image_dir,
                models_dir,
                o,
                input_path=out_dir / "input",
                next_image_callback=registered,
            )
        timings["mapping"] = time.perf_counter() - t0
        if models:
            rec = max(models.values(), key=lambda r: r.num_reg_images())
        else:
            logger.warning("the mapper returned no model: keeping the seeded input model")
            rec = seed
        dropped = drop_ill_determined(
            rec,
            registered_ground(seed),
            conf["max_position_std_m"],
            priors,
            prior_std,
            conf["pos_limits"] or transfer_default_conf["pnp"],
        )
        if dropped:
            logger.info(
                "%d ground images registered by the mapper dropped: %s",
                len(dropped),
                ", ".join(f"{g} ({v})" for g, v in sorted(dropped.items())),
            )
        added = add_pnp_images(rec, db_path, ids, offsets, ag, pnp, conf) if conf["add_pnp_images"] else []
        if added:
            logger.info(
                "%d ground images localized by the reducer's PnP but without pairs strong enough for the"
                " mapper added at their PnP pose: %s",
                len(added),
                ", ".join(added),
            )

    with stage("combined:georef", logger):
        frame = read_georef_frame(aerial_dir / "georef.json")
        records = {r.name: r for r in read_pos(pos) if r.name.startswith("aerial/")}
        geo_summary = None
        if conf["georef"] and not conf["mapping"]["fix_aerial"]:
            sigma = (
                float(np.median([r.std_or_default()[0] for r in records.values()]))
                if records
                else DEFAULT_STD_XY
            )
            try:
                geo = georef_mod.georeference(rec, records, frame, sigma)
                geo_summary = {**georef_mod.summary(geo), "method": geo.method}
            except georef_mod.GeorefError as e:
                logger.warning("georeferencing failed: %s", e)
        sparse = out_dir / "sparse"
        if sparse.exists():
            shutil.rmtree(sparse)
        sparse.mkdir(parents=True)
        rec.write(str(sparse))
        shutil.copy(aerial_dir / "georef.json", out_dir / "georef.json")

    report = build_report(
        rec,
        ids,
        priors,
        pnp,
        seed,
        geo_summary,
        timings,
        t_all,
        added,
        dropped,
        conf["mapping"]["fix_aerial"],
        pair_sizes,
        int(conf["mapping"]["min_num_matches"]),
    )
    report["ground_pairs"] = gg_records
    if conf["gis"]:
        with stage("combined:gis", logger):
            report["gis"] = write_gis(rec, frame, pos, report, aerial_dir, out_dir / "gis")
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    logger.info(
        "combined model: NRI aerial %s, ground %s; N3P %d; reprojection error %.2f px -> %s",
        report["NRI"]["aerial"],
        report["NRI"]["ground"],
        report["num_points3D"],
        report["mean_reprojection_error_px"],
        sparse,
    )
    prog(1.0, "done")
    return sparse


def write_gis(rec, frame, pos, report: dict, aerial_dir: Path, out: Path) -> dict:
    """GeoPackage, GeoJSON, omega/phi/kappa and LAS outputs (services.sfm.gis) in the aerial SfM's output
    CRS (else the POS CRS, else UTM); a failure is logged and reported, the model stays."""
    from services.pos import read_pos
    from services.sfm import gis

    try:
        crs_doc = json.loads((aerial_dir / "georef.json").read_text()).get("crs") or {}
        records = {r.name: r for r in read_pos(pos)}
        return gis.main(rec, frame, records, report, out, crs_doc.get("output") or crs_doc.get("pos"))
    except Exception as e:  # noqa: BLE001 - the reconstruction is the result; its exports are extras
        logger.warning("GIS outputs not written: %s", e)
        return {"error": f"{type(e).__name__}: {e}"}


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
    tracks (see the module docstring); written to `out`."""
    db = pycolmap.Database.open(str(db_path))
    try:
        db_images = {im.image_id: im for im in db.read_all_images()}
        db_cams = {c.camera_id: c for c in db.read_all_cameras()}
        kps = {i: db.read_keypoints(i)[:, :2].astype(np.float64) for i in db_images}
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for cam_id in sorted(db_cams):
        rec.add_camera_with_trivial_rig(db_cams[cam_id])
    # the aerial model's cameras (refined intrinsics, if any) override the database's
    for cam_id, cam in aerial.cameras.items():
        if cam_id in db_cams:
            rec.cameras[cam_id].params = cam.params
    by_name = {im.name: im for im in aerial.images.values() if im.has_pose}
    registered: set[str] = set()
    for name, img in sorted(by_name.items()):
        iid = ids[name]
        if iid != img.image_id:
            raise RuntimeError(f"{name}: image id {img.image_id} in the aerial model, {iid} in its database")
        im = pycolmap.Image(name=name, keypoints=kps[iid], camera_id=img.camera_id, image_id=iid)
        rec.add_image_with_trivial_frame(im, img.cam_from_world())
        registered.add(name)
    ground_cam_id = next((db_images[ids[n]].camera_id for n in ids if n.startswith("ground/")), None)
    if conf["seed_pnp_poses"]:
        min_pair = max(int(conf["mapping"]["min_num_matches"]), int(conf["min_seed_matches"]))
        for g, r in sorted(pnp.items()):
            # the mapper only keeps images with a pair of at least min_num_matches correspondences
            if not r.get("accepted") or g not in ids or pair_sizes.get(ids[g], 0) < min_pair:
                continue
            if conf["seed_pnp_poses"] == "trusted" and not rests_on_trusted_depth(r, conf):
                continue
            iid = ids[g]
            im = pycolmap.Image(name=g, keypoints=kps[iid], camera_id=ground_cam_id, image_id=iid)
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(r["R"], float)), np.asarray(r["t"], float))
            rec.add_image_with_trivial_frame(im, pose)
            registered.add(g)
    # every other database image, unregistered (the mapper expects a frame for each)
    present = set(by_name) | registered
    for iid, dbim in sorted(db_images.items()):
        if dbim.name in present:
            continue
        im = pycolmap.Image(name=dbim.name, keypoints=kps[iid], camera_id=dbim.camera_id, image_id=iid)
        rec.add_image_with_trivial_frame(im)
    for _, p in sorted(aerial.points3D.items()):
        rec.add_point3D(p.xyz, pycolmap.Track(p.track.elements), p.color)
    n_seed = 0
    if conf["seed_points"]:
        n_seed = _seed_tracks(rec, ids, offsets, ag, kps, registered)
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


def drop_ill_determined(
    rec: pycolmap.Reconstruction,
    fixed: set[str],
    max_std: float | None,
    priors: dict[str, Pose] | None = None,
    prior_std: dict[str, tuple[float, float, float]] | None = None,
    pnp_conf: dict | None = None,
) -> dict[str, str]:
    """Deregister the ground images the mapper registered (not those of `fixed`, held at the reducer's
    PnP pose) whose pose disagrees with their POS (with `priors` and `pnp_conf`, the reducer's POS
    limits, services.reduce: a repeated facade can register an image far from where it was taken), or
    whose centre the model determines worse than `max_std` metres: the standard deviation along the
    worst direction from the covariance of the model's bundle adjustment with the other images held
    (services.pose_uncertainty.joint_position_stds), so a run of ground images tied by their own points
    but placed by a few ill-spread aerial points is judged by those. Dropping an image can leave the
    others less determined: repeated until none is dropped. Returns {name: reason}."""
    from services.pose_uncertainty import fit_position_std, joint_position_stds
    from services.reduce import prior_agreement

    def candidates() -> list[pycolmap.Image]:
        return [
            im
            for im in rec.images.values()
            if im.name.startswith("ground/") and im.has_pose and im.name not in fixed
        ]

    out: dict[str, str] = {}
    if priors and pnp_conf:
        for im in candidates():
            if im.name in priors:
                std = (prior_std or {}).get(im.name)
                reasons = prior_agreement(pose_of_image(im), priors[im.name], std, pnp_conf)[2]
                if reasons:
                    rec.deregister_frame(im.frame_id)
                    out[im.name] = "; ".join(reasons)
    while max_std:
        ims = candidates()
        stds = joint_position_stds(rec, [im.image_id for im in ims]) if ims else {}
        if stds is None:  # a singular problem: each image with its own points held fixed
            stds = {}
            for im in ims:
                obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
                stds[im.image_id] = fit_position_std(
                    pose_of_image(im),
                    np.asarray(im.camera.calibration_matrix()),
                    np.array([o[0] for o in obs], float).reshape(-1, 2),
                    np.array([o[1] for o in obs], float).reshape(-1, 3),
                )
        bad = [im for im in ims if stds.get(im.image_id, 0.0) > max_std]
        for im in bad:
            rec.deregister_frame(im.frame_id)
            out[im.name] = f"position ill-determined (std {stds[im.image_id]:.2f} m)"
        if not bad:
            break
    return out


def add_pnp_images(
    rec: pycolmap.Reconstruction,
    db_path: Path,
    ids: dict[str, int],
    offsets: dict[str, int],
    ag: list[tuple[str, str, np.ndarray]],
    pnp: dict[str, dict],
    conf: dict,
) -> list[str]:
    """Add to `rec` the ground images whose PnP pose the reducer accepted but the mapper did not
    register, at that pose; each observes the model's 3D points that its transferred matches reach
    (the aerial keypoint's point, reprojecting within `add_max_px`). Returns the names added."""
    todo = [g for g, r in sorted(pnp.items()) if r.get("accepted") and g in ids]
    registered = {im.name for im in rec.images.values() if im.has_pose}
    todo = [g for g in todo if g not in registered]
    if not todo:
        return []
    db = pycolmap.Database.open(str(db_path))
    try:
        db_images = {n: db.read_image(ids[n]) for n in todo}
        kps = {n: db.read_keypoints(ids[n])[:, :2].astype(np.float64) for n in todo}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
    finally:
        db.close()
    aerial_p3d: dict[str, dict[int, int]] = {}  # aerial name -> keypoint -> point3D id
    for im in rec.images.values():
        if im.name in offsets and im.has_pose:
            aerial_p3d[im.name] = {k: p.point3D_id for k, p in enumerate(im.points2D) if p.has_point3D()}
    added = []
    for g in todo:
        dbim = db_images[g]
        if dbim.camera_id not in rec.cameras:
            rec.add_camera_with_trivial_rig(cams[dbim.camera_id])
        r = pnp[g]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(r["R"], float)), np.asarray(r["t"], float))
        if ids[g] in rec.images:  # unregistered in the model (the input model: the mapper made none)
            frame_id = rec.images[ids[g]].frame_id
            rec.frames[frame_id].rig_from_world = pose  # trivial rig: the camera is the rig
            rec.register_frame(frame_id)
        else:
            im = pycolmap.Image(name=g, keypoints=kps[g], camera_id=dbim.camera_id, image_id=ids[g])
            rec.add_image_with_trivial_frame(im, pose)
        added.append(g)
    # observations: of the aerial keypoint's point where it has one, else of a new two-view point
    all_kps: dict[int, np.ndarray] = {ids[g]: kps[g] for g in added}
    used: set[tuple[int, int]] = set()  # (ground image id, point3D id or -keypoint - 1)
    new_tracks: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for a, g, m in ag:
        if ids.get(g) not in all_kps or a not in aerial_p3d:
            continue
        gid = ids[g]
        P = _projection(rec.images[gid])
        for ia, ig in m:
            akp = int(ia) + offsets[a]
            if (gid, -int(ig) - 1) in used:
                continue
            pid = aerial_p3d[a].get(akp)
            if pid is None:
                new_tracks.setdefault((ids[a], akp), []).append((gid, int(ig)))
                continue
            if (gid, pid) in used:
                continue
            x = P @ np.append(rec.points3D[pid].xyz, 1.0)
            if x[2] <= 0 or np.linalg.norm(x[:2] / x[2] - kps[g][ig]) > conf["add_max_px"]:
                continue
            rec.add_observation(pid, pycolmap.TrackElement(gid, int(ig)))
            used |= {(gid, pid), (gid, -int(ig) - 1)}
    for (aid, akp), gobs in sorted(new_tracks.items()):
        if aid not in all_kps:
            all_kps[aid] = np.array([p.xy for p in rec.images[aid].points2D], np.float64)
        obs = [(aid, akp)]
        for gid, ig in gobs:
            if (gid, -ig - 1) not in used and all(gid != i for i, _ in obs):
                obs.append((gid, ig))
        if len(obs) < 2:
            continue
        X = _triangulate(rec, obs, all_kps, conf["add_max_px"])
        if X is None or _max_angle_deg(rec, X, [i for i, _ in obs]) < conf["add_min_angle_deg"]:
            continue
        rec.add_point3D(
            X, pycolmap.Track([pycolmap.TrackElement(i, k) for i, k in obs]), np.full(3, 128, np.uint8)
        )
        used |= {(gid, -ig - 1) for gid, ig in obs[1:]}
    return added


def _max_angle_deg(rec: pycolmap.Reconstruction, X: np.ndarray, image_ids: list[int]) -> float:
    """The largest angle (degrees) at X between the rays of the images `image_ids`."""
    d = np.array([np.asarray(rec.images[i].projection_center()) - X for i in image_ids])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((d @ d.T).min(), -1.0, 1.0))))


def _projection(image: pycolmap.Image) -> np.ndarray:
    """The 3x4 projection matrix K [R | t] of a posed image (pinhole part of its camera)."""
    return np.asarray(image.camera.calibration_matrix()) @ np.asarray(image.cam_from_world().matrix())


def _seed_tracks(
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
        X = _triangulate(rec, obs, kps)
        if X is None:
            continue
        track = pycolmap.Track([pycolmap.TrackElement(i, k) for i, k in obs])
        rec.add_point3D(X, track, np.array([128, 128, 128], np.uint8))
        n += 1
    return n


def _triangulate(
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
        P = _projection(img)
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


def build_report(
    rec: pycolmap.Reconstruction,
    ids: dict[str, int],
    priors: dict[str, Pose],
    pnp: dict[str, dict],
    seed: pycolmap.Reconstruction,
    georef: dict | None,
    timings: dict,
    t_all: float,
    added: list[str] | None = None,
    dropped: dict[str, str] | None = None,
    conf_fixed: bool = True,
    pair_sizes: dict[int, int] | None = None,
    min_pair_matches: int = 15,
) -> dict:
    reg = {im.name: im for im in rec.images.values() if im.has_pose}
    seeded = registered_ground(seed)
    if not conf_fixed:
        seeded = set()  # refined by the mapper's bundle adjustment: no longer the PnP pose
    sets = {
        "aerial": sorted(n for n in ids if n.startswith("aerial/")),
        "ground": sorted(n for n in ids if n.startswith("ground/")),
    }
    nri = {s: f"{sum(n in reg for n in names)}/{len(names)}" for s, names in sets.items()}
    ground = {}
    for g in sets["ground"]:
        d: dict[str, Any] = {"registered": g in reg}
        if g in reg:
            # "pnp": at the reducer's PnP pose (seeded, kept fixed by the mapper, or added after it)
            d["registered_by"] = "pnp" if g in (added or []) or g in seeded else "mapper"
            d["observations"] = int(reg[g].num_points3D)
            c = np.asarray(reg[g].projection_center())
            d["center"] = c.tolist()
            if g in priors:
                d["to_pos_m"] = float(np.linalg.norm(c - priors[g].center))
            if pnp.get(g, {}).get("accepted"):
                d["to_pnp_m"] = float(np.linalg.norm(c - np.asarray(pnp[g]["center"], float)))
        elif g in (dropped or {}):
            d["reason"] = f"registered by the mapper but dropped: {dropped[g]}"
        else:
            largest = (pair_sizes or {}).get(ids[g], 0)
            if pnp.get(g, {}).get("accepted"):
                d["reason"] = "registered by PnP but dropped by the mapper"
            elif pair_sizes is not None and largest >= min_pair_matches:
                d["reason"] = (
                    f"verified pairs (the largest {largest} matches), but too few of its matches reach"
                    " 3D points of the registered images for the mapper to localize it"
                )
            else:
                d["reason"] = (
                    "no verified aerial-ground or ground-ground pair of at least"
                    f" {min_pair_matches} matches to register it"
                )
        ground[g] = d
    return {
        "NRI": nri,
        "num_registered": {s: sum(n in reg for n in names) for s, names in sets.items()},
        "num_images": {s: len(names) for s, names in sets.items()},
        "num_points3D": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "added_pnp_ground_images": sorted(added or []),
        "seeded_ground_images": len(registered_ground(seed)),
        "georef": georef,
        "ground": ground,
        "timings_s": {
            **{k: round(v, 2) for k, v in timings.items()},
            "total": round(time.perf_counter() - t_all, 2),
        },
    }
