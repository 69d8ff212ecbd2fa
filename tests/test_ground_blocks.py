"""services.sfm.combined.blocks: chains of ground images the mapper left out, placed as one block on
their ties to the aerial points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose
from services.geometry import look_at
from services.sfm.combined import CombinedDatabase, default_conf
from services.sfm.combined.blocks import (
    block_pose,
    chain_ties,
    fit_block,
    ties_reason,
    unregistered_chains,
)

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
BC = default_conf["blocks"]


def _walk(n: int) -> dict[str, Pose]:
    """n ground cameras 3.5 m apart along a street, looking at a facade 10 m away."""
    return {
        f"ground/G{i:04d}.jpg": look_at(np.array([3.5 * i, 0.0, 1.6]), np.array([3.5 * i, 10.0, 3.0]))
        for i in range(n)
    }


def test_the_chains_are_the_unregistered_images_joined_by_verified_pairs():
    walk = _walk(7)
    names = sorted(walk)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    for i, n in enumerate(names, start=1):
        im = pycolmap.Image(name=n, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i)
        if i <= 2:  # G0000 and G0001 registered
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(walk[n].R), walk[n].t))
        else:
            rec.add_image_with_trivial_frame(im)
    g = names
    pairs = {
        f"{g[1]} {g[2]}": {"accepted": True},  # a registered image does not join a chain
        f"{g[2]} {g[3]}": {"accepted": True},
        f"{g[3]} {g[4]}": {"accepted": True},
        f"{g[4]} {g[5]}": {"accepted": False},  # refused: not a link
        f"{g[5]} {g[6]}": {"accepted": True},
    }
    ids = {n: i for i, n in enumerate(names, start=1)}
    cdb = CombinedDatabase(Path("unused.db"), ids, {}, {}, {}, ground_pairs=pairs)
    assert unregistered_chains(rec, cdb, 3) == [[g[2], g[3], g[4]]]
    assert unregistered_chains(rec, cdb, 2) == [[g[2], g[3], g[4]], [g[5], g[6]]]


def test_a_block_is_placed_by_the_ties_of_two_of_its_images_not_of_one():
    """The similarity model_from_block comes back from ties with a third of them wrong; a block whose
    agreeing ties all come through one image is not placed (one image's matches can be a repeated
    facade shifted by a window)."""
    rng = np.random.default_rng(3)
    truth = pycolmap.Sim3d(
        2.5, pycolmap.Rotation3d(look_at(np.zeros(3), np.array([1.0, 2.0, 0.3])).R), [5.0, -3.0, 1.0]
    )
    Y = rng.uniform(-10, 10, (90, 3))
    X = np.array([truth * y for y in Y]) + rng.normal(0, 0.05, (90, 3))
    X[60:] += rng.uniform(2.0, 6.0, (30, 3))  # wrong ties
    who = ["ground/G0003.jpg"] * 45 + ["ground/G0004.jpg"] * 45
    sim, agree = fit_block(Y, X, BC)
    assert sim is not None and abs(sim.scale - 2.5) < 0.02
    assert agree[:60].mean() > 0.95 and agree[60:].sum() <= 2
    images = sorted({w for w, ok in zip(who, agree, strict=True) if ok})
    assert ties_reason((int(agree.sum()), len(Y)), images, BC) == ""
    assert "through 1 of its images" in ties_reason((40, 45), ["ground/G0003.jpg"], BC)
    assert "ties agree" in ties_reason((12, 40), images, BC)  # too few ties


def test_a_block_camera_sees_the_model_as_it_saw_the_block():
    """block_pose: a point of the block frame and its image in a block camera; the camera placed in the
    model's frame sees the point mapped by the similarity at the same pixel."""
    sim = pycolmap.Sim3d(
        0.8, pycolmap.Rotation3d(look_at(np.zeros(3), np.array([0.3, 1.0, -0.2])).R), [10.0, 4.0, -2.0]
    )
    pose = _walk(3)["ground/G0002.jpg"]
    im = pycolmap.Image(name="ground/G0002.jpg", keypoints=np.zeros((0, 2)), camera_id=1, image_id=1)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    placed = block_pose(rec.images[1], sim)
    Xb = np.array([[7.0, 9.0, 2.0], [6.0, 11.0, 4.5]])
    uv_block, _ = pose.project(CAM.K, Xb)
    uv_model, _ = placed.project(CAM.K, np.array([sim * x for x in Xb]))
    assert np.allclose(uv_block, uv_model, atol=1e-6)
    assert np.allclose(placed.center, sim * pose.center)


def _model_with_points(poses: dict[str, Pose], ids: dict[str, int], X: np.ndarray) -> pycolmap.Reconstruction:
    """A reconstruction of the images `poses`, keypoint k of each the projection of X[k], one point per
    row of X observed by every image."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    for n, pose in poses.items():
        uv, _ = pose.project(CAM.K, X)
        im = pycolmap.Image(name=n, keypoints=np.asarray(uv, float), camera_id=1, image_id=ids[n])
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    for k, x in enumerate(X):
        rec.add_point3D(x, pycolmap.Track([pycolmap.TrackElement(ids[n], k) for n in poses]))
    return rec


def test_a_block_is_tied_to_the_registered_ground_images_it_shares_verified_pairs_with(tmp_path):
    """A block image's keypoints matched (a verified ground-ground pair in the database) to those of a
    registered walk image tie the block's points to the model's points that image sees; a refused pair
    ties nothing."""
    walk = _walk(4)
    names = sorted(walk)
    ids = {n: i for i, n in enumerate(names, start=1)}
    rng = np.random.default_rng(0)
    X = np.stack([rng.uniform(0, 10, 40), rng.uniform(9.0, 10.0, 40), rng.uniform(0, 6, 40)], 1)
    rec = _model_with_points({n: walk[n] for n in names[:2]}, ids, X)  # G0000, G0001 registered
    sim = pycolmap.Sim3d(0.5, pycolmap.Rotation3d(np.eye(3)), [1.0, 2.0, 3.0])  # block_from_model
    block_poses = {}
    for n in names[2:]:
        C = sim * walk[n].center
        block_poses[n] = Pose(walk[n].R, -walk[n].R @ C)
    block = _model_with_points(block_poses, ids, np.array([sim * x for x in X]))
    db = pycolmap.Database.open(str(tmp_path / "c.db"))
    cid = db.write_camera(CAM.to_pycolmap(1))
    for n in names:
        db.write_image(pycolmap.Image(name=n, camera_id=cid, image_id=ids[n]), use_image_id=True)
    tvg = pycolmap.TwoViewGeometry()
    tvg.config = 2
    tvg.inlier_matches = np.stack([np.arange(30), np.arange(30)], 1).astype(np.uint32)  # keypoint k to k
    db.write_two_view_geometry(ids[names[1]], ids[names[2]], tvg)
    db.write_two_view_geometry(ids[names[0]], ids[names[3]], tvg)
    db.close()
    pairs = {f"{names[1]} {names[2]}": {"accepted": True}, f"{names[0]} {names[3]}": {"accepted": False}}
    cdb = CombinedDatabase(tmp_path / "c.db", ids, {}, {}, {}, ground_pairs=pairs)
    Y, Xm, who = chain_ties(block, rec, cdb)
    assert len(Y) == 30 and {w[0] for w in who} == {names[2]}  # through the accepted pair only
    assert np.allclose(Xm, X[:30]) and np.allclose(Y, [sim * x for x in X[:30]])
    fitted, agree = fit_block(Y, Xm, BC)
    assert fitted is not None and agree.all() and abs(fitted.scale - 2.0) < 1e-6


def _two_view_database(path: Path, walk: dict[str, Pose], n_points: int = 150) -> list[str]:
    """A database of the walk's cameras where each pair of neighbours shares its own n_points facade
    points, every point seen by those two images only (a walk's ground-ground matches)."""
    rng = np.random.default_rng(8)
    names = sorted(walk)
    db = pycolmap.Database.open(str(path))
    cam_id = db.write_camera(CAM.to_pycolmap(1))
    rig = pycolmap.Rig()
    rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id))
    rig_id = db.write_rig(rig)
    kps: dict[str, list[np.ndarray]] = {n: [] for n in names}
    pairs = []
    for a, b in zip(names, names[1:], strict=False):
        mid = (walk[a].center + walk[b].center) / 2
        X = np.stack(
            [mid[0] + rng.uniform(-4, 4, n_points), np.full(n_points, 10.0), rng.uniform(0, 6, n_points)], 1
        )
        start = {n: sum(len(k) for k in kps[n]) for n in (a, b)}
        for n in (a, b):
            kps[n].append(walk[n].project(CAM.K, X)[0])
        idx = np.arange(n_points)
        pairs.append((a, b, np.stack([start[a] + idx, start[b] + idx], 1)))
    ids = {}
    for n in names:
        ids[n] = db.write_image(pycolmap.Image(name=n, camera_id=cam_id))
        frame = pycolmap.Frame()
        frame.rig_id = rig_id
        frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id), ids[n]))
        db.write_frame(frame)
        db.write_keypoints(ids[n], np.concatenate(kps[n]).astype(np.float32))
    for a, b, m in pairs:
        db.write_matches(ids[a], ids[b], m)
        geometry = pycolmap.TwoViewGeometry()
        geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        geometry.inlier_matches = m
        R = walk[b].R @ walk[a].R.T
        geometry.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(R), walk[b].t - R @ walk[a].t)
        db.write_two_view_geometry(ids[a], ids[b], geometry)
    db.close()
    return names


def test_a_chain_whose_points_two_images_see_reconstructs(tmp_path):
    """Two ground images share points no third image sees: COLMAP 4 skips such two-view tracks by
    default, so a chain's initial pair got no point at all and no chain was ever reconstructed; the
    combined SfM's mapping triangulates them (mapping.two_view_tracks)."""
    from services.sfm.combined.blocks import reconstruct_chain
    from services.sfm.combined.mapping import mapper_options

    names = _two_view_database(tmp_path / "db.db", _walk(2))
    mc = default_conf["mapping"]
    assert mc["two_view_tracks"]
    model = reconstruct_chain(tmp_path / "db.db", tmp_path, tmp_path / "block", names, mapper_options(mc))
    assert model is not None and model.num_reg_images() == 2 and model.num_points3D() == 150
    skipped = mapper_options({**mc, "two_view_tracks": False})
    model = reconstruct_chain(tmp_path / "db.db", tmp_path, tmp_path / "block2", names, skipped)
    assert model is None or model.num_reg_images() == 0
