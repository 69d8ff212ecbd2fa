"""Ground images localized as a block (services.ground_block): each image sees its 2D-3D correspondences
on one small patch of facade, so its own pose is ill-determined (metres), but the street of images held
together by a ground-only model pins one similarity to centimetres."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from services import ground_block, transfer
from services.colmap_model import Camera, Pose
from services.pose_uncertainty import fit_position_std
from services.viewpoints import look_at

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
STD = (2.5, 4.0, 2.0)
PNP_CONF = transfer.default_conf["pnp"]
# the ground model's frame: x_model = S0 R0 X + T0 (an arbitrary similarity of the aerial frame)
S0, T0 = 0.37, np.array([3.0, -1.0, 0.5])
R0 = look_at(np.zeros(3), np.array([1.0, 2.0, 0.3])).R


def _street(n: int = 6) -> dict[str, Pose]:
    """Ground cameras 4 m apart along a street (x), 1.6 m high, looking at a facade 10 m away (y)."""
    return {
        f"ground/G{i:04d}.jpg": look_at(
            np.array([4.0 * i, 0.0, 1.6]), np.array([4.0 * i + 3 * (i % 2), 10.0, 3.0])
        )
        for i in range(n)
    }


def _model(true: dict[str, Pose], jitter_m: float = 0.0, seed: int = 0) -> pycolmap.Reconstruction:
    """A ground-only model of the cameras `true`, in the frame of (S0, R0, T0), centres jittered."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    for i, (name, p) in enumerate(sorted(true.items()), start=1):
        c = p.center + rng.normal(0, jitter_m, 3)
        R = p.R @ R0.T
        t = -R @ (S0 * R0 @ c + T0)
        im = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    return rec


def _patch(pose: Pose, rng, n: int = 25, outliers: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """n keypoints on a 90 px patch of the facade (y = 10) with their points, plus wrong points."""
    u0, v0 = rng.uniform(200, 824), rng.uniform(150, 450)
    kp = np.stack([rng.uniform(u0, u0 + 90, n), rng.uniform(v0, v0 + 90, n)], 1)
    d = pose.R.T @ np.linalg.solve(CAM.K, np.concatenate([kp, np.ones((n, 1))], 1).T)  # world rays
    X = pose.center + (d * ((10.0 - pose.center[1]) / d[1])).T
    kp = kp + rng.normal(0, 0.5, kp.shape)
    if outliers:
        kp = np.concatenate([kp, rng.uniform(0, [1024, 768], (outliers, 2))])
        X = np.concatenate([X, X[:outliers] + rng.normal(0, 2.0, (outliers, 3))])
    return kp, X


def _priors(true: dict[str, Pose], seed: int = 1):
    rng = np.random.default_rng(seed)
    priors = {
        n: Pose.from_center(p.R.T, p.center + rng.normal(0, 1.5, 3) * [1, 1, 0.3]) for n, p in true.items()
    }
    return priors, {n: STD for n in true}


def test_patches_leave_each_image_ill_determined_but_the_block_pins_them():
    true = _street()
    rng = np.random.default_rng(0)
    corr = {n: _patch(p, rng) for n, p in sorted(true.items()) if n != "ground/G0003.jpg"}
    # alone, each image's centre is uncertain by far more than the 0.25 m the reducer accepts
    for n, (kp, X) in corr.items():
        assert fit_position_std(true[n], CAM.K, kp[:25], X[:25]) > 0.25
    priors, std = _priors(true)
    res = ground_block.localize_block({}, _model(true), corr, CAM, priors, std, PNP_CONF)
    assert res["ok"], res["reason"]
    assert res["num_inliers"] >= 5 * 25 - 5 and res["images_with_inliers"] == 5
    assert res["scale"] == pytest.approx(S0, rel=0.01)
    for n, d in res["images"].items():  # G0003, without correspondences, is placed by the block too
        assert d["accepted"], (n, d["reason"])
        assert np.linalg.norm(np.asarray(d["center"]) - true[n].center) < 0.1
        assert d["position_std_m"] < 0.25
        assert np.allclose(np.asarray(d["R"]), true[n].R, atol=1e-2)


def test_a_block_with_correspondences_in_one_image_is_that_image_alone():
    true = _street()
    rng = np.random.default_rng(2)
    n0 = "ground/G0002.jpg"
    corr = {n0: _patch(true[n0], rng, n=60, outliers=0)}
    priors, std = _priors(true)
    res = ground_block.localize_block({}, _model(true), corr, CAM, priors, std, PNP_CONF)
    assert not res["ok"] and "inliers in 1 images" in res["reason"]
    assert not any(d["accepted"] for d in res["images"].values())


def test_a_model_whose_scale_disagrees_with_the_pos_is_rejected():
    true = _street()
    rng = np.random.default_rng(3)
    corr = {n: _patch(p, rng) for n, p in sorted(true.items())}
    # the POS of a street 1.7 times as long: the similarity's scale and the POS's disagree
    priors = {n: Pose.from_center(p.R.T, 1.7 * p.center) for n, p in true.items()}
    conf = {"scale_search": [0.6, 1.0]}
    res = ground_block.localize_block(conf, _model(true), corr, CAM, priors, {n: STD for n in true}, PNP_CONF)
    assert res["scale"] == pytest.approx(S0, rel=0.01)
    assert not res["ok"] and "disagree" in res["reason"]


def test_no_correspondences_gives_a_reason():
    true = _street()
    priors, std = _priors(true)
    res = ground_block.localize_block({}, _model(true), {}, CAM, priors, std, PNP_CONF)
    assert not res["ok"] and res["reason"] == "no 2D-3D correspondences in the block"
    assert res["images"] == {}


def test_ground_points_round_trip(tmp_path):
    pts = {"ground/a b.jpg": {"keypoints": np.array([3, 1]), "X": np.arange(6.0).reshape(2, 3)}}
    path = transfer.write_ground_points(tmp_path / "ground_points.npz", pts)
    back = transfer.read_ground_points(path)
    assert list(back) == ["ground/a b.jpg"]
    assert np.array_equal(back["ground/a b.jpg"]["keypoints"], [3, 1])
    assert np.array_equal(back["ground/a b.jpg"]["X"], pts["ground/a b.jpg"]["X"])
    assert transfer.read_ground_points(tmp_path / "missing.npz") == {}


def _database(path, true: dict[str, Pose], seed: int = 0) -> dict[str, np.ndarray]:
    """A COLMAP database of the ground images `true` as services.combined_sfm writes it: keypoints of
    facade points, each image matched with its next two, the pairs' relative poses. Returns keypoints."""
    from services import combined_sfm

    rng = np.random.default_rng(seed)
    n = 3000
    P = np.stack([rng.uniform(-10, 32, n), 10.0 + rng.uniform(0, 3, n), rng.uniform(0, 12, n)], 1)
    db = pycolmap.Database.open(str(path))
    names = sorted(true)
    ids = combined_sfm._write_ground(db, CAM, names)
    seen, kps = {}, {}
    for name in names:
        uv, z = true[name].project(CAM.K, P)
        idx = np.flatnonzero((z > 0) & (uv >= 0).all(1) & (uv[:, 0] < CAM.width) & (uv[:, 1] < CAM.height))
        kps[name] = uv[idx] + rng.normal(0, 0.3, (len(idx), 2))
        db.write_keypoints(ids[name], kps[name].astype(np.float32))
        seen[name] = {int(p): k for k, p in enumerate(idx)}
    for i, a in enumerate(names):
        for b in names[i + 1 : i + 3]:
            common = sorted(set(seen[a]) & set(seen[b]))
            m = np.array([[seen[a][p], seen[b][p]] for p in common])
            R = true[b].R @ true[a].R.T
            t = true[b].t - R @ true[a].t
            rel = {"R": R.tolist(), "t": (t / np.linalg.norm(t)).tolist()}
            combined_sfm._write_pair(db, ids[a], ids[b], m, None, True, rel)
    db.close()
    return kps


def test_main_builds_the_ground_model_and_localizes_it(tmp_path):
    true = _street()
    kps = _database(tmp_path / "database.db", true)
    rng = np.random.default_rng(4)
    points = {}
    for name in ("ground/G0001.jpg", "ground/G0004.jpg"):  # two images with a patch each
        kp, X = _patch(true[name], rng)
        # the reducer's points refer to the image's keypoints: append the patch's keypoints to them
        points[name] = {"keypoints": len(kps[name]) + np.arange(len(kp)), "X": X}
        kps[name] = np.concatenate([kps[name], kp])
    priors, std = _priors(true)
    report = ground_block.main(
        {}, tmp_path / "database.db", tmp_path, kps, points, CAM, priors, std, PNP_CONF, tmp_path / "block"
    )
    (block,) = report["blocks"]
    assert block["ok"], block["reason"]
    assert sorted(report["images"]) == sorted(true)
    for name, d in report["images"].items():
        assert np.linalg.norm(np.asarray(d["center"]) - true[name].center) < 0.15, name


def test_mapper_registrations_far_from_their_pos_are_dropped():
    """services.combined_sfm.drop_ill_determined: a ground image the mapper registered on well-spread
    points is still dropped when its pose is 20 m from its POS (a repeated facade); one near it stays."""
    from services.combined_sfm import drop_ill_determined

    true = _street(2)
    rng = np.random.default_rng(5)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    for i, (name, p) in enumerate(sorted(true.items()), start=1):
        kp = np.stack([rng.uniform(50, 974, 80), rng.uniform(50, 718, 80)], 1)
        X = p.unproject(CAM.K, kp, rng.uniform(8.0, 20.0, 80))
        im = pycolmap.Image(name=name, keypoints=kp, camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(p.R), p.t))
        for k in range(len(kp)):
            rec.add_point3D(X[k], pycolmap.Track([pycolmap.TrackElement(i, k)]), np.zeros(3, np.uint8))
    priors = {n: Pose.from_center(p.R.T, p.center) for n, p in true.items()}
    priors["ground/G0001.jpg"] = Pose.from_center(true["ground/G0001.jpg"].R.T, np.array([4.0, 20.0, 1.6]))
    dropped = drop_ill_determined(rec, {}, 0.25, priors, {n: STD for n in true}, PNP_CONF)
    assert list(dropped) == ["ground/G0001.jpg"] and "from the POS" in dropped["ground/G0001.jpg"]
    assert rec.find_image_with_name("ground/G0000.jpg").has_pose
    assert not rec.find_image_with_name("ground/G0001.jpg").has_pose
    # an image at an accepted PnP pose is the reducer's to judge: kept
    rec2 = pycolmap.Reconstruction(rec)
    assert (
        drop_ill_determined(rec2, {"ground/G0000.jpg": {"accepted": True}}, 0.25, priors, None, PNP_CONF)
        == {}
    )
