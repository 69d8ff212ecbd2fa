"""The combined SfM's mapping: pycolmap's incremental mapper continuing from the input model, then the
ground images it registered but the model leaves uncertain or far from their POS dropped, and those the
reducer localized added at their PnP pose where the mapper left them out."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pycolmap

from services.colmap_model import Pose
from services.geometry import pose_of_image
from services.sfm.combined.database import CombinedDatabase
from services.sfm.combined.model import (
    max_angle_deg,
    pose_of_record,
    projection,
    registered_ground,
    triangulate,
)
from services.sfm.combined.refine import refine_ground

logger = logging.getLogger("midview.combined_sfm")


def drop_ill_determined(
    rec: pycolmap.Reconstruction,
    fixed: set[str],
    max_std: float | None,
    priors: dict[str, Pose] | None = None,
    prior_std: dict[str, tuple[float, float, float]] | None = None,
    pnp_conf: dict | None = None,
    db_path: Path | None = None,
    ambiguity: dict | None = None,
    partners: dict[str, set[str]] | None = None,
) -> dict[str, str]:
    """Deregister the ground images the mapper registered (not those of `fixed`, held at the reducer's
    PnP pose) whose pose disagrees with their POS (with `priors` and `pnp_conf`, the reducer's POS
    limits, services.reduce: a repeated facade can register an image far from where it was taken), whose
    verified matches (`db_path`'s) fit two poses alike (with `ambiguity`, services.sfm.combined.ambiguity:
    half of a pair's matches a window along the street), whose points nearly all one other ground image
    observes with no other verified pair (`partners`) to a registered image (`ambiguity`'s
    hanging_min_share: the pose of one unchecked pair), or whose centre the model determines worse than
    `max_std` metres: the standard deviation along the worst direction from the covariance of the model's
    bundle adjustment with the other images held (services.pose_uncertainty.joint_position_stds), so a
    run of ground images tied by their own points but placed by a few ill-spread aerial points is judged
    by those. Dropping an image can leave the others less determined: repeated until none is dropped.
    Returns {name: reason}."""
    from services.pose_uncertainty import fit_pose_stds, joint_position_stds
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
    if db_path is not None and ambiguity:
        from services.sfm.combined.ambiguity import ambiguous_images

        for image_id, hyp in ambiguous_images(
            rec, [im.image_id for im in candidates()], str(db_path), ambiguity
        ).items():
            im = rec.images[image_id]
            rec.deregister_frame(im.frame_id)
            out[im.name] = hyp.reason()
    from services.sfm.combined.ambiguity import hanging_images

    while ambiguity and ambiguity.get("hanging_min_share"):  # dropping one can leave another hanging
        ids = [im.image_id for im in candidates()]
        hanging = hanging_images(rec, ids, ambiguity["hanging_min_share"], partners)
        for image_id, why in hanging.items():
            im = rec.images[image_id]
            rec.deregister_frame(im.frame_id)
            out[im.name] = why
        if not hanging:
            break
    while max_std:
        ims = candidates()
        stds = joint_position_stds(rec, [im.image_id for im in ims]) if ims else {}
        if stds is None:  # a singular problem: each image with its own points held fixed
            stds = {}
            for im in ims:
                obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
                stds[im.image_id] = fit_pose_stds(
                    pose_of_image(im),
                    np.asarray(im.camera.calibration_matrix()),
                    np.array([o[0] for o in obs], float).reshape(-1, 2),
                    np.array([o[1] for o in obs], float).reshape(-1, 3),
                )[0]
        bad = [im for im in ims if stds.get(im.image_id, 0.0) > max_std]
        for im in bad:
            rec.deregister_frame(im.frame_id)
            out[im.name] = f"position ill-determined (std {stds[im.image_id]:.2f} m)"
        if not bad:
            break
    return out


def _register_at(
    rec: pycolmap.Reconstruction, todo: list[str], db_path: Path, ids: dict[str, int], poses: dict[str, dict]
) -> dict[str, np.ndarray]:
    """Register the ground images `todo` in `rec` at their pose (a record R, t: the reducer's PnP pose, a
    block's); their keypoints (N, 2) by name."""
    db = pycolmap.Database.open(str(db_path))
    try:
        db_images = {n: db.read_image(ids[n]) for n in todo}
        kps = {n: db.read_keypoints(ids[n])[:, :2].astype(np.float64) for n in todo}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
    finally:
        db.close()
    for g in todo:
        dbim = db_images[g]
        if dbim.camera_id not in rec.cameras:
            rec.add_camera_with_trivial_rig(cams[dbim.camera_id])
        r = poses[g]
        pose = pose_of_record(r)
        if ids[g] in rec.images:  # unregistered in the model (the input model: the mapper made none)
            frame_id = rec.images[ids[g]].frame_id
            rec.frames[frame_id].rig_from_world = pose  # trivial rig: the camera is the rig
            rec.register_frame(frame_id)
        else:
            im = pycolmap.Image(name=g, keypoints=kps[g], camera_id=dbim.camera_id, image_id=ids[g])
            rec.add_image_with_trivial_frame(im, pose)
    return kps


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
    register, at that pose (add_at_poses). Returns the names added."""
    registered = {im.name for im in rec.images.values() if im.has_pose}
    todo = {g: r for g, r in sorted(pnp.items()) if r.get("accepted") and g in ids and g not in registered}
    return add_at_poses(rec, todo, db_path, ids, offsets, ag, conf)


def add_at_poses(
    rec: pycolmap.Reconstruction,
    poses: dict[str, dict],
    db_path: Path,
    ids: dict[str, int],
    offsets: dict[str, int],
    ag: list[tuple[str, str, np.ndarray]],
    conf: dict,
) -> list[str]:
    """Register the ground images of `poses` ({name: cam_from_world record R, t}) in `rec` at those
    poses; each observes the model's 3D points that its transferred matches reach (the aerial keypoint's
    point, reprojecting within `add_max_px`), or new two-view points where the aerial keypoint has none.
    Returns the names added."""
    todo = sorted(poses)
    if not todo:
        return []
    kps = _register_at(rec, todo, db_path, ids, poses)
    aerial_p3d: dict[str, dict[int, int]] = {}  # aerial name -> keypoint -> point3D id
    for im in rec.images.values():
        if im.name in offsets and im.has_pose:
            aerial_p3d[im.name] = {k: p.point3D_id for k, p in enumerate(im.points2D) if p.has_point3D()}
    all_kps: dict[int, np.ndarray] = {ids[g]: kps[g] for g in todo}
    used: set[tuple[int, int]] = set()  # (ground image id, point3D id or -keypoint - 1)
    new_tracks = _observe_points(rec, ag, ids, offsets, aerial_p3d, all_kps, used, conf["add_max_px"])
    _add_new_points(rec, new_tracks, all_kps, used, conf)
    return todo


def _observe_points(
    rec: pycolmap.Reconstruction,
    ag: list[tuple[str, str, np.ndarray]],
    ids: dict[str, int],
    offsets: dict[str, int],
    aerial_p3d: dict[str, dict[int, int]],
    all_kps: dict[int, np.ndarray],
    used: set[tuple[int, int]],
    max_px: float,
) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """The added images observe the aerial keypoints' points (within max_px); the matches whose aerial
    keypoint has no point: {(aerial id, keypoint): [(ground id, keypoint)]}."""
    new_tracks: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for a, g, m in ag:
        if ids.get(g) not in all_kps or a not in aerial_p3d:
            continue
        gid = ids[g]
        P = projection(rec.images[gid])
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
            if x[2] <= 0 or np.linalg.norm(x[:2] / x[2] - all_kps[gid][ig]) > max_px:
                continue
            rec.add_observation(pid, pycolmap.TrackElement(gid, int(ig)))
            used |= {(gid, pid), (gid, -int(ig) - 1)}
    return new_tracks


def _add_new_points(
    rec: pycolmap.Reconstruction,
    new_tracks: dict[tuple[int, int], list[tuple[int, int]]],
    all_kps: dict[int, np.ndarray],
    used: set[tuple[int, int]],
    conf: dict,
) -> None:
    """A new point per aerial keypoint and the added images' keypoints matched to it, triangulated
    (within add_max_px) and seen under add_min_angle_deg at least."""
    for (aid, akp), gobs in sorted(new_tracks.items()):
        if aid not in all_kps:
            all_kps[aid] = np.array([p.xy for p in rec.images[aid].points2D], np.float64)
        obs = [(aid, akp)]
        for gid, ig in gobs:
            if (gid, -ig - 1) not in used and all(gid != i for i, _ in obs):
                obs.append((gid, ig))
        if len(obs) < 2:
            continue
        X = triangulate(rec, obs, all_kps, conf["add_max_px"])
        if X is None or max_angle_deg(rec, X, [i for i, _ in obs]) < conf["add_min_angle_deg"]:
            continue
        rec.add_point3D(
            X, pycolmap.Track([pycolmap.TrackElement(i, k) for i, k in obs]), np.full(3, 128, np.uint8)
        )
        used |= {(gid, -ig - 1) for gid, ig in obs[1:]}


def mapper_options(mc: dict) -> pycolmap.IncrementalPipelineOptions:
    """pycolmap's incremental mapping options from conf["mapping"]: one model, the input model's
    frames fixed (fix_aerial), intrinsics refined or not, points of two images triangulated or not."""
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
    o.triangulation.ignore_two_view_tracks = not bool(mc.get("two_view_tracks", False))
    refine = bool(mc["refine_intrinsics"])
    o.ba_refine_focal_length = refine
    o.ba_refine_extra_params = refine
    o.ba_refine_principal_point = False
    o.mapper.abs_pose_refine_focal_length = refine
    o.mapper.abs_pose_refine_extra_params = refine
    return o


def run_mapper(
    db_path: Path,
    image_dir: Path,
    out_dir: Path,
    seed: pycolmap.Reconstruction,
    n_total: int,
    conf: dict,
    prog,
) -> pycolmap.Reconstruction:
    """pycolmap's incremental mapper continuing from the input model (out_dir/input); its largest model,
    or the input model when it made none. prog(fraction, message) after each registered image."""
    models_dir = out_dir / "models"
    if models_dir.exists():
        shutil.rmtree(models_dir)
    models_dir.mkdir(parents=True)
    state = {"n": seed.num_reg_images()}

    def registered() -> None:
        state["n"] += 1
        prog(min(state["n"] / max(n_total, 1), 1.0), f"{state['n']} images registered")

    models = pycolmap.incremental_mapping(  # the caller holds glog's warnings (colmap_log_level)
        db_path,
        image_dir,
        models_dir,
        mapper_options(conf["mapping"]),
        input_path=out_dir / "input",
        next_image_callback=registered,
    )
    if models:
        return max(models.values(), key=lambda r: r.num_reg_images())
    logger.warning("the mapper returned no model: keeping the seeded input model")
    return seed


def settle_ground(
    rec: pycolmap.Reconstruction,
    seed: pycolmap.Reconstruction,
    cdb: CombinedDatabase,
    pnp: dict[str, dict],
    pos_limits: dict,
    conf: dict,
) -> tuple[dict[str, str], list[str], dict[str, float]]:
    """After the mapper: (dropped {name: reason}, added [name], refined {name: metres moved}): the chained
    ground images refined with the aerial images held (refine_ground), the ground images the mapper registered
    that the model leaves uncertain or that disagree with their POS dropped (drop_ill_determined; the
    seeds stay), then those the reducer localized added at their PnP pose (add_pnp_images)."""
    refined = {}
    if conf["refine_ground"]["enabled"]:
        refined = refine_ground(rec, conf["refine_ground"])
        if refined:
            moved = sorted(refined.values())
            logger.info(
                "%d ground images refined with the aerial images held: moved %.2f m median, %.2f m max",
                len(moved),
                moved[len(moved) // 2],
                moved[-1],
            )
    held = registered_ground(seed)
    max_std = conf["max_position_std_m"]
    partners: dict[str, set[str]] = {}  # each ground image's verified ground pairs
    for key, pair in cdb.ground_pairs.items():
        # "g0 g1": split where both sides are image names (a name may hold a space)
        split = [(key[:i], key[i + 1 :]) for i, c in enumerate(key) if c == " "]
        named = [(a, b) for a, b in split if a in cdb.ids and b in cdb.ids]
        if pair.get("accepted") and named:
            g0, g1 = named[0]
            partners.setdefault(g0, set()).add(g1)
            partners.setdefault(g1, set()).add(g0)
    dropped = drop_ill_determined(
        rec, held, max_std, cdb.priors, cdb.prior_std, pos_limits, cdb.path, conf["ambiguity"], partners
    )
    refined = {g: m for g, m in refined.items() if g not in dropped}
    if dropped:
        logger.info(
            "%d ground images registered by the mapper dropped: %s",
            len(dropped),
            ", ".join(f"{g} ({v})" for g, v in sorted(dropped.items())),
        )
    added = []
    if conf["add_pnp_images"]:
        added = add_pnp_images(rec, cdb.path, cdb.ids, cdb.offsets, cdb.ag, pnp, conf)
    if added:
        logger.info(
            "%d ground images localized by the reducer's PnP but without pairs strong enough for the"
            " mapper added at their PnP pose: %s",
            len(added),
            ", ".join(added),
        )
    return dropped, added, refined
