"""Checks of the combined reconstruction's database and model (services.sfm.combined): its ground-ground
pairs, with their two-view geometries, are a database COLMAP's own mapper reconstructs the ground images
from; ground images the mapper registers far from their POS are dropped."""

from __future__ import annotations

import numpy as np
import pycolmap

from services import reduce as transfer
from services.colmap_model import Camera, Pose
from services.conf import merge_conf
from services.geometry import look_at

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
STD = (2.5, 4.0, 2.0)
PNP_CONF = transfer.default_conf["pnp"]


def _street(n: int = 6) -> dict[str, Pose]:
    """Ground cameras 4 m apart along a street (x), 1.6 m high, looking at a facade 10 m away (y)."""
    return {
        f"ground/G{i:04d}.jpg": look_at(
            np.array([4.0 * i, 0.0, 1.6]), np.array([4.0 * i + 3 * (i % 2), 10.0, 3.0])
        )
        for i in range(n)
    }


def _database(path, true: dict[str, Pose], seed: int = 0) -> dict[str, np.ndarray]:
    """A COLMAP database of the ground images `true` as services.sfm.combined writes it: keypoints of
    facade points, each image matched with its next two, with the pair's relative pose (as
    verify_ground_pair finds it). Returns the keypoints."""
    from services.sfm import combined as combined_sfm

    rng = np.random.default_rng(seed)
    n = 3000
    P = np.stack([rng.uniform(-10, 32, n), 10.0 + rng.uniform(0, 3, n), rng.uniform(0, 12, n)], 1)
    db = pycolmap.Database.open(str(path))
    names = sorted(true)
    ids = combined_sfm.write_ground(db, CAM, names)
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
            combined_sfm.write_pair(db, ids[a], ids[b], m, None, True, rel)
    db.close()
    return kps


def test_colmaps_mapper_reconstructs_the_ground_images_from_the_database(tmp_path):
    true = _street()
    _database(tmp_path / "database.db", true)
    o = pycolmap.IncrementalPipelineOptions()
    o.extract_colors = False
    o.ba_refine_focal_length = False
    o.ba_refine_principal_point = False
    o.ba_refine_extra_params = False
    models = pycolmap.incremental_mapping(tmp_path / "database.db", tmp_path, tmp_path / "models", o)
    assert len(models) == 1 and models[0].num_reg_images() == len(true)
    # the model is the street up to a similarity: its camera centres keep their relative distances
    rec = models[0]
    c = np.array([rec.find_image_with_name(n).projection_center() for n in sorted(true)])
    c_true = np.array([true[n].center for n in sorted(true)])
    d, d_true = np.linalg.norm(c - c[0], axis=1)[1:], np.linalg.norm(c_true - c_true[0], axis=1)[1:]
    assert np.allclose(d / d[-1], d_true / d_true[-1], atol=0.01)
    # the stored two-view geometry is the pair's relative pose
    db = pycolmap.Database.open(str(tmp_path / "database.db"))
    ids = {im.name: im.image_id for im in db.read_all_images()}
    a, b = sorted(true)[:2]
    tvg = db.read_two_view_geometry(ids[a], ids[b])
    db.close()
    R_true = true[b].R @ true[a].R.T
    assert np.allclose(np.asarray(tvg.cam2_from_cam1.rotation.matrix()), R_true, atol=1e-6)


def test_mapper_registrations_far_from_their_pos_are_dropped():
    """services.sfm.combined.drop_ill_determined: a ground image the mapper registered on well-spread
    points is still dropped when its pose is 20 m from its POS (a repeated facade); one near it stays."""
    from services.sfm.combined import drop_ill_determined

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
    # (no uncertainty check: the points here are seen by one image each, the POS check alone)
    dropped = drop_ill_determined(rec, set(), None, priors, {n: STD for n in true}, PNP_CONF)
    assert list(dropped) == ["ground/G0001.jpg"] and "from the POS" in dropped["ground/G0001.jpg"]
    assert rec.find_image_with_name("ground/G0000.jpg").has_pose
    assert not rec.find_image_with_name("ground/G0001.jpg").has_pose
    # an image held at its PnP pose (seeded) is the reducer's to judge: kept
    rec2 = pycolmap.Reconstruction(rec)
    assert drop_ill_determined(rec2, {"ground/G0000.jpg"}, 0.25, priors, None, PNP_CONF) == {}


def test_the_report_says_why_a_ground_image_is_not_registered():
    from services.sfm.combined import build_report

    true = _street(3)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    ids = {}
    for i, (name, p) in enumerate(sorted(true.items()), start=1):
        im = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i)
        if i == 1:  # the first one registered, the others not
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(p.R), p.t))
        else:
            rec.add_image_with_trivial_frame(im)
        ids[name] = i
    g0, g1, g2 = sorted(true)
    rep = build_report(
        rec,
        ids,
        {},
        {},
        pycolmap.Reconstruction(),
        None,
        {},
        0.0,
        pair_sizes={2: 264, 3: 9},
        min_pair_matches=15,
    )
    assert rep["NRI"]["ground"] == "1/3" and rep["ground"][g0]["registered"]
    assert "the largest 264 matches" in rep["ground"][g1]["reason"]
    assert "no verified aerial-ground or ground-ground pair of at least 15" in rep["ground"][g2]["reason"]


def _anchored_street(patch: bool, seed: int = 0) -> tuple[pycolmap.Reconstruction, dict[str, int]]:
    """Three ground images 4 m apart tied by 300 facade points they share (no aerial view of those) and
    placed by 40 points two fixed aerial cameras see too: on a 1 m patch of the facade (`patch`) or
    spread over it. Exact keypoints. Returns the model and {name: image id}."""
    rng = np.random.default_rng(seed)
    aerial_cam = Camera("PINHOLE", 1600, 1200, [1300.0, 1300.0, 800.0, 600.0])
    cams = {
        "aerial/A0000.jpg": (aerial_cam, look_at(np.array([-10.0, -25.0, 45.0]), np.array([4.0, 10.0, 3.0]))),
        "aerial/A0001.jpg": (aerial_cam, look_at(np.array([20.0, -25.0, 45.0]), np.array([4.0, 10.0, 3.0]))),
    }
    cams.update({n: (CAM, p) for n, p in _street(3).items()})
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(aerial_cam.to_pycolmap(1))
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(2))
    if patch:
        anchors = np.stack([rng.uniform(0, 1, 40), np.full(40, 10.0), rng.uniform(2, 3, 40)], 1)
    else:
        anchors = np.stack([rng.uniform(-3, 3, 40), np.full(40, 10.0), rng.uniform(0.5, 6, 40)], 1)
    shared = np.stack([rng.uniform(-2, 11, 300), np.full(300, 10.0), rng.uniform(0.5, 6, 300)], 1)
    views = {n: [] for n in cams}  # (keypoint, point index)
    points = [*anchors, *shared]
    for j in range(len(anchors)):
        for n in cams:
            views[n].append(j)
    for j in range(len(anchors), len(points)):
        for n in sorted(n for n in cams if n.startswith("ground/")):
            views[n].append(j)
    ids = {}
    tracks: dict[int, list] = {}
    for i, (name, (cam, pose)) in enumerate(sorted(cams.items()), start=1):
        P = np.array([points[j] for j in views[name]])
        uv, z = pose.project(cam.K, P)
        ok = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
        im = pycolmap.Image(name=name, keypoints=uv, camera_id=1 if cam is aerial_cam else 2, image_id=i)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
        ids[name] = i
        for k, j in enumerate(views[name]):
            if ok[k]:
                tracks.setdefault(j, []).append(pycolmap.TrackElement(i, k))
    for j, els in sorted(tracks.items()):
        if len(els) >= 2:
            rec.add_point3D(points[j], pycolmap.Track(els), np.zeros(3, np.uint8))
    return rec, ids


def test_a_run_of_ground_images_placed_by_a_patch_is_ill_determined():
    """services.pose_uncertainty.joint_position_stds: ground images tied by hundreds of their own points
    but placed by a 1 m patch that the aerial images see are as uncertain as the patch leaves them (each
    image alone, with its points held fixed, looks well determined); placed by points spread over the
    facade they are determined, and drop_ill_determined keeps them."""
    from services.pose_uncertainty import fit_pose_stds, joint_position_stds
    from services.sfm.combined import drop_ill_determined

    rec, ids = _anchored_street(patch=True)
    ground = [ids[n] for n in sorted(ids) if n.startswith("ground/")]
    stds = joint_position_stds(rec, ground)
    im = rec.images[ids["ground/G0002.jpg"]]
    obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
    m = np.asarray(im.cam_from_world().matrix())
    alone = fit_pose_stds(
        Pose(m[:, :3], m[:, 3]), CAM.K, np.array([o[0] for o in obs]), np.array([o[1] for o in obs])
    )[0]
    assert alone < 0.1 < 1.0 < min(stds.values())
    dropped = drop_ill_determined(rec, set(), 0.5)
    assert sorted(dropped) == ["ground/G0000.jpg", "ground/G0001.jpg", "ground/G0002.jpg"]
    assert all("ill-determined" in r for r in dropped.values())

    rec, ids = _anchored_street(patch=False)
    stds = joint_position_stds(rec, ground)
    assert max(stds.values()) < 0.5
    assert drop_ill_determined(rec, set(), 0.5) == {}
    assert all(rec.images[i].has_pose for i in ground)


def test_transferred_tracks_are_seeded_for_ground_images_not_registered_yet():
    """services.sfm.combined.seed_tracks: a transferred track is triangulated from its registered
    observations; the keypoints of a ground image the reducer did not localize link its aerial
    observations but stay out of the track (the mapper then sees that image's 2D-3D correspondences and
    can register it); once that image is registered its keypoints join the track."""
    from services.sfm.combined import seed_tracks

    rng = np.random.default_rng(2)
    aerial_cam = Camera("PINHOLE", 1600, 1200, [1300.0, 1300.0, 800.0, 600.0])
    poses = {
        "aerial/A0000.jpg": look_at(np.array([-10.0, -25.0, 45.0]), np.array([4.0, 10.0, 3.0])),
        "aerial/A0001.jpg": look_at(np.array([20.0, -25.0, 45.0]), np.array([4.0, 10.0, 3.0])),
        "ground/G0000.jpg": _street(1)["ground/G0000.jpg"],
    }
    X = np.stack([rng.uniform(-2, 6, 30), np.full(30, 10.0), rng.uniform(0.5, 6, 30)], 1)
    ids = {n: i for i, n in enumerate(sorted(poses), start=1)}
    offsets = {"aerial/A0000.jpg": 7, "aerial/A0001.jpg": 7, "ground/G0000.jpg": 0}
    kps = {}
    for n, p in poses.items():
        uv, _ = p.project(CAM.K if n.startswith("ground/") else aerial_cam.K, X)
        kps[ids[n]] = np.concatenate([np.zeros((offsets[n], 2)), uv])  # the aerial SfM keypoints first
    m = np.stack([np.arange(30), np.arange(30)], 1)
    ag = [("aerial/A0000.jpg", "ground/G0000.jpg", m), ("aerial/A0001.jpg", "ground/G0000.jpg", m)]

    def model(registered: set[str]) -> pycolmap.Reconstruction:
        rec = pycolmap.Reconstruction()
        rec.add_camera_with_trivial_rig(aerial_cam.to_pycolmap(1))
        rec.add_camera_with_trivial_rig(CAM.to_pycolmap(2))
        for n, i in ids.items():
            im = pycolmap.Image(
                name=n, keypoints=kps[i], camera_id=1 if n.startswith("aerial/") else 2, image_id=i
            )
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(poses[n].R), poses[n].t)
            rec.add_image_with_trivial_frame(*((im, pose) if n in registered else (im,)))
        return rec

    aerial = {"aerial/A0000.jpg", "aerial/A0001.jpg"}
    rec = model(aerial)
    assert seed_tracks(rec, ids, offsets, ag, kps, aerial) == 30
    for p in rec.points3D.values():
        els = sorted((e.image_id, e.point2D_idx) for e in p.track.elements)
        k = els[0][1] - 7
        assert els == [(1, k + 7), (2, k + 7)]  # the two aerial keypoints, at the offset
        assert np.allclose(p.xyz, X[k], atol=1e-6)
    rec = model(aerial | {"ground/G0000.jpg"})
    assert seed_tracks(rec, ids, offsets, ag, kps, aerial | {"ground/G0000.jpg"}) == 30
    assert all(p.track.length() == 3 for p in rec.points3D.values())


def test_the_input_model_holds_the_pnp_poses_its_seeding_mode_takes(tmp_path):
    """services.sfm.combined.build_input_model: with seed_pnp_poses "trusted" (the default) only the
    accepted PnP poses that rest on trusted rendered depth start registered; True takes every accepted
    pose with a pair the mapper keeps, False none."""
    from services.sfm import combined as combined_sfm

    aerial_cam = Camera("PINHOLE", 1600, 1200, [1300.0, 1300.0, 800.0, 600.0])
    true = {
        "aerial/A0000.jpg": look_at(np.array([0.0, -25.0, 45.0]), np.array([4.0, 10.0, 3.0])),
        **_street(3),
    }
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    ids = {
        **combined_sfm.write_ground(db, aerial_cam, ["aerial/A0000.jpg"]),
        **combined_sfm.write_ground(db, CAM, sorted(n for n in true if n.startswith("ground/"))),
    }
    for i in ids.values():
        db.write_keypoints(i, np.random.default_rng(i).uniform(0, 700, (50, 2)).astype(np.float32))
    db.close()
    aerial = pycolmap.Reconstruction()
    aerial.add_camera_with_trivial_rig(aerial_cam.to_pycolmap(1))
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(true["aerial/A0000.jpg"].R), true["aerial/A0000.jpg"].t)
    aerial.add_image_with_trivial_frame(
        pycolmap.Image(name="aerial/A0000.jpg", camera_id=1, image_id=ids["aerial/A0000.jpg"]), pose
    )

    def pnp(name: str, trusted: int, accepted: bool = True) -> dict:
        p = true[name]
        return {"accepted": accepted, "R": p.R.tolist(), "t": p.t.tolist(), "num_inliers": 40,
                "trusted_depth_inliers": trusted}  # fmt: skip

    poses = {
        "ground/G0000.jpg": pnp("ground/G0000.jpg", 40),  # on the exact rendered depth
        "ground/G0001.jpg": pnp("ground/G0001.jpg", 0),  # on points triangulated through the renders
        "ground/G0002.jpg": pnp("ground/G0002.jpg", 40, accepted=False),
    }
    pair_sizes = dict.fromkeys(ids.values(), 100)

    def seeded(mode) -> set[str]:
        conf = merge_conf(combined_sfm.default_conf, {"seed_pnp_poses": mode, "seed_points": False})
        out = tmp_path / f"input-{mode}"
        rec = combined_sfm.build_input_model(
            aerial, tmp_path / "db.db", ids, {}, [], poses, pair_sizes, conf, out
        )
        return combined_sfm.registered_ground(rec)

    assert combined_sfm.default_conf["seed_pnp_poses"] == "trusted"
    assert seeded("trusted") == {"ground/G0000.jpg"}
    assert seeded(True) == {"ground/G0000.jpg", "ground/G0001.jpg"}
    assert seeded(False) == set()
    pair_sizes[ids["ground/G0000.jpg"]] = 5  # no pair the mapper keeps
    assert seeded("trusted") == set()


def test_the_last_adjustment_moves_a_run_placed_by_an_offset_seed_to_the_aerial_points():
    """services.sfm.combined.refine_ground: three ground images and the facade points they share, all
    0.5 m off (a seed's PnP pose off by that much, its neighbours registered through the points it placed),
    come back to within centimetres of the truth, held by the 40 points two fixed aerial cameras see;
    the aerial cameras do not move, and images that share too few points with other ground images stay
    held."""
    from services.sfm.combined import default_conf
    from services.sfm.combined.refine import refine_ground

    rec, ids = _anchored_street(patch=False)
    truth = {n: np.asarray(rec.images[i].projection_center()) for n, i in ids.items()}
    offset = np.array([0.3, -0.2, 0.35])
    for n, i in ids.items():
        if n.startswith("ground/"):
            im = rec.images[i]
            m = np.asarray(im.cam_from_world().matrix())
            R, t = m[:, :3], m[:, 3] - m[:, :3] @ offset  # the centre moved by `offset`
            rec.frames[im.frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
    for p in rec.points3D.values():
        if all(rec.images[e.image_id].name.startswith("ground/") for e in p.track.elements):
            p.xyz = p.xyz + offset
    conf = merge_conf(default_conf["refine_ground"], {"min_shared_observations": 15})
    moved = refine_ground(rec, conf)
    assert sorted(moved) == sorted(n for n in ids if n.startswith("ground/"))
    for n, i in ids.items():
        err = np.linalg.norm(np.asarray(rec.images[i].projection_center()) - truth[n])
        assert err < (1e-9 if n.startswith("aerial/") else 0.05), (n, err)
    assert all(0.4 < m < 0.6 for m in moved.values())

    rec, ids = _anchored_street(patch=False)
    before = {n: np.asarray(rec.images[i].projection_center()) for n, i in ids.items()}
    assert refine_ground(rec, merge_conf(conf, {"min_shared_observations": 10_000})) == {}
    assert all(np.allclose(rec.images[i].projection_center(), before[n]) for n, i in ids.items())
