"""The reducer (services/reduce/) on hand-made match tables and on a constructed 3D scene."""

from __future__ import annotations

import numpy as np
import pytest

from services import reduce as transfer
from services.colmap_model import Camera, Pose
from services.pos import ypr_to_matrix
from shared.matchfile import MatchFile, PairMatches

A, G, G2 = "aerial/A0001.jpg", "ground/G0001.jpg", "ground/G0002.jpg"
CAM = Camera("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0])
IDENTITY = Pose(np.eye(3), np.zeros(3))
# no 3D checks: the hand-made tables have no geometry
PLAIN = {"aerial_px": None, "pnp": {"enabled": False}, "fundamental": {"enabled": False}}


def pair(name0, name1, rows, inliers=None):
    """rows: (render idx, image idx, score)."""
    m = np.array([[r[0], r[1]] for r in rows], np.int32).reshape(-1, 2)
    s = np.array([r[2] for r in rows], np.float32)
    inl = np.ones(len(m), bool) if inliers is None else np.asarray(inliers, bool)
    return PairMatches(name0, name1, m, s, inl)


def view(name, pairs, n_render=20, depth=None, camera=CAM, pose=IDENTITY, kps=None):
    r = f"views/{name}.png"
    keypoints = {r: np.zeros((n_render, 2), np.float32)}
    for n in (A, G, G2):
        keypoints[n] = np.zeros((50, 2), np.float32) if kps is None else kps[n]
    if kps is not None and r in kps:
        keypoints[r] = kps[r]
    return transfer.ViewData(name, camera, pose, depth, keypoints, [p(r) for p in pairs])


def reduce(views, conf=PLAIN):
    pairs, _, poses, stats = transfer.reduce_views(views, {}, {}, CAM, {}, {}, conf)
    return pairs, poses, stats


def as_set(p):
    return {(int(a), int(g)) for a, g in p["matches"]}


def test_shared_render_keypoints_transfer_and_one_sided_ones_do_not():
    v = view(
        "V1",
        [
            lambda r: pair(r, A, [(0, 5, 0.9), (1, 6, 0.8), (2, 7, 0.7)]),
            lambda r: pair(r, G, [(0, 15, 0.9), (2, 17, 0.6), (3, 18, 0.9)]),
        ],
    )
    pairs, _, stats = reduce([v])
    assert list(pairs) == [(A, G)]
    p = pairs[(A, G)]
    assert as_set(p) == {(5, 15), (7, 17)}  # render kp 1 (aerial only) and 3 (ground only) do not transfer
    k = {tuple(m): i for i, m in enumerate(p["matches"].tolist())}
    assert p["scores"][k[(7, 17)]] == pytest.approx(0.6)  # the weaker of the two render matches
    assert stats["views"] == ["V1"] and (p["views"] == 0).all()


def test_outliers_of_the_render_matches_are_not_transferred():
    v = view(
        "V1",
        [
            lambda r: pair(r, A, [(0, 5, 0.9), (1, 6, 0.8)], inliers=[True, False]),
            lambda r: pair(r, G, [(0, 15, 0.9), (1, 16, 0.8)]),
        ],
    )
    pairs, _, _ = reduce([v])
    assert as_set(pairs[(A, G)]) == {(5, 15)}


def test_one_to_one_and_duplicates_across_views():
    v1 = view(
        "V1",
        [
            lambda r: pair(r, A, [(0, 5, 0.9), (1, 6, 0.9), (2, 8, 0.5)]),
            lambda r: pair(r, G, [(0, 15, 0.9), (1, 16, 0.9), (2, 18, 0.5)]),
        ],
    )
    v2 = view(
        "V2",
        [
            # (5, 15) again through V2 (a duplicate), (5, 19) conflicts with it on the aerial side with a
            # lower score, (9, 16) conflicts with (6, 16) on the ground side with a higher score
            lambda r: pair(r, A, [(3, 5, 0.95), (4, 5, 0.4), (5, 9, 0.99)]),
            lambda r: pair(r, G, [(3, 15, 0.95), (4, 19, 0.4), (5, 16, 0.99)]),
        ],
    )
    pairs, _, _ = reduce([v1, v2])
    p = pairs[(A, G)]
    got = as_set(p)
    assert got == {(5, 15), (9, 16), (8, 18)}
    ia, ig = p["matches"][:, 0], p["matches"][:, 1]
    assert len(set(ia)) == len(ia) and len(set(ig)) == len(ig)  # one-to-one
    k = {tuple(m): i for i, m in enumerate(p["matches"].tolist())}
    assert p["views"][k[(5, 15)]] == 1  # the higher-scored duplicate (through V2) is kept
    assert p["views"][k[(8, 18)]] == 0


def test_ties_are_broken_by_view_name():
    mk = lambda name: view(  # noqa: E731
        name, [lambda r: pair(r, A, [(0, 5, 0.7)]), lambda r: pair(r, G, [(0, 15, 0.7)])]
    )
    pairs, _, stats = reduce([mk("V2"), mk("V1")])
    p = pairs[(A, G)]
    assert as_set(p) == {(5, 15)}
    assert stats["views"][int(p["views"][0])] == "V1"


def random_views(seed: int, n_views: int = 6) -> list[transfer.ViewData]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_views):
        pairs = []
        for other in (A, G, G2):
            rows = [
                (int(r), int(rng.integers(0, 50)), float(rng.choice([0.5, 0.7, 0.9])))
                for r in rng.choice(20, 12, replace=False)
            ]
            pairs.append(lambda r, other=other, rows=rows: pair(r, other, rows))
        out.append(view(f"V{i}", pairs))
    return out


def test_order_independence(tmp_path):
    views = random_views(0)
    ref, _, ref_stats = reduce(views)
    assert set(ref) == {(A, G), (A, G2)}
    for k in range(3):
        perm = np.random.default_rng(k).permutation(len(views))
        got, _, stats = reduce([views[i] for i in perm])
        assert stats["views"] == ref_stats["views"]
        assert list(got) == list(ref)
        for key in ref:
            for f in ("matches", "scores", "inliers", "views"):
                np.testing.assert_array_equal(got[key][f], ref[key][f])
    # and the written match file holds the pairs aerial first, with the views
    kps = {n: np.zeros((50, 2), np.float32) for n in (A, G, G2)}
    sizes = {A: (640, 480), G: (640, 480), G2: (640, 480)}
    path = transfer.write_match_file(tmp_path / "m.h5", ref, kps, sizes, ref_stats["views"])
    with MatchFile(path) as mf:
        assert mf.pairs() == [(A, G), (A, G2)]
        assert mf.views == ref_stats["views"]
        pm = mf.get_pair(A, G)
        np.testing.assert_array_equal(pm.views, ref[(A, G)]["views"])


# -- 3D verification on a constructed scene ----------------------------------------------------------
def look_at(center, target) -> Pose:
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    return Pose.from_center(np.stack([x, np.cross(z, x), z], 1), center)


def test_pnp_verification_rejects_wrong_matches_and_localizes_the_ground_camera():
    rng = np.random.default_rng(1)
    wall_y = 20.0  # a facade at y = 20, the render and both cameras look at it
    target = np.array([0.0, wall_y, 6.0])
    render_pose = look_at(np.array([0.0, 0.0, 12.0]), target)
    aerial_pose = look_at(np.array([5.0, -25.0, 45.0]), target)
    ground_pose = look_at(np.array([-2.0, 8.0, 1.6]), target + [0, 0, -3.0])
    aerial_cam = Camera("PINHOLE", 800, 600, [700.0, 700.0, 400.0, 300.0])
    # the render's depth: ray / wall intersection for every pixel
    h, w = CAM.height, CAM.width
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    uv = np.stack([jj.ravel(), ii.ravel()], 1)
    rays = render_pose.unproject(CAM.K, uv, np.ones(len(uv))) - render_pose.center
    t = (wall_y - render_pose.center[1]) / rays[:, 1]
    depth = t.reshape(h, w).astype(np.float32)  # unproject with depth 1 gives z = 1: t is the z-depth
    # render keypoints in the middle of the image, their 3D points and projections
    n = 60
    kp_r = np.stack([rng.uniform(100, 540, n), rng.uniform(80, 400, n)], 1).astype(np.float32)
    X = render_pose.unproject(CAM.K, kp_r.astype(float), np.array([depth[int(y), int(x)] for x, y in kp_r]))
    kp_a, _ = aerial_pose.project(aerial_cam.K, X)
    kp_g, _ = ground_pose.project(CAM.K, X)
    kp_g = kp_g + rng.normal(0, 0.3, kp_g.shape)
    # 15 wrong ground matches (random ground keypoints) among the 60
    bad = np.arange(45, 60)
    kp_g[bad] = np.stack([rng.uniform(0, w, 15), rng.uniform(0, h, 15)], 1)
    kps = {
        "views/V1.png": kp_r,
        A: kp_a.astype(np.float32),
        G: kp_g.astype(np.float32),
        G2: np.zeros((1, 2), np.float32),
    }
    rows = [(i, i, 0.9) for i in range(n)]
    v = view(
        "V1",
        [lambda r: pair(r, A, rows), lambda r: pair(r, G, rows)],
        n_render=n,
        depth=depth,
        pose=render_pose,
        kps=kps,
    )
    # the POS of the ground camera: 2 m and 2 degrees off
    R_noise = ypr_to_matrix(2.0, 0.0, 0.0) @ ypr_to_matrix(0.0, 0.0, 0.0).T
    prior = Pose.from_center(R_noise @ ground_pose.R.T, ground_pose.center + [1.5, -1.2, 0.5])
    # one view's matches alone make no pose by default (pnp.min_other_view_inliers), but a consensus that
    # verifies them; the pose says which view its inliers came through
    pairs, _, poses, _ = transfer.reduce_views(
        [v], {A: aerial_cam}, {A: aerial_pose}, CAM, {G: prior}, {G: (2.5, 4.0, 2.0)}
    )
    assert not poses[G]["accepted"] and poses[G]["consensus"]
    assert "one view's matches alone" in poses[G]["reason"]
    assert poses[G]["inlier_views"] == {"V1": poses[G]["num_inliers"]} and poses[G]["num_inliers"] >= 40
    kept = set(pairs[(A, G)]["matches"][pairs[(A, G)]["inliers"], 1].tolist())
    assert kept >= set(range(40)) and not kept & set(bad.tolist())
    # the same matches through two views (the render split in two) make a pose
    halves = {"V1": [r for r in rows if r[0] % 2 == 0], "V2": [r for r in rows if r[0] % 2 == 1]}
    two = [
        view(name, [lambda r, h=h: pair(r, A, h), lambda r, h=h: pair(r, G, h)], n_render=n, depth=depth,
             pose=render_pose, kps={**kps, f"views/{name}.png": kp_r})
        for name, h in halves.items()
    ]  # fmt: skip
    # every point has one aerial image: its depth is the render's surface, 13 m from the ground camera,
    # whose scale the reducer counts as 5% uncertain (pnp.depth_scale_std): 0.66 m along that line
    _, _, poses, _ = transfer.reduce_views(
        two, {A: aerial_cam}, {A: aerial_pose}, CAM, {G: prior}, {G: (2.5, 4.0, 2.0)}
    )
    assert not poses[G]["accepted"] and 0.5 < poses[G]["position_std_m"] < 0.8, poses[G]["reason"]
    assert set(poses[G]["inlier_views"]) == {"V1", "V2"}
    exact = {"pnp": {"depth_scale_std": 0.0}}  # the surface here is exact: without that nuisance
    _, _, poses, _ = transfer.reduce_views(
        two, {A: aerial_cam}, {A: aerial_pose}, CAM, {G: prior}, {G: (2.5, 4.0, 2.0)}, exact
    )
    assert poses[G]["accepted"], poses[G]["reason"]
    # the checks below are those of one view's pose: the rule above off
    one_view = {"pnp": {"min_other_view_inliers": 0, "depth_scale_std": 0.0}}
    pairs, _, poses, stats = transfer.reduce_views(
        [v], {A: aerial_cam}, {A: aerial_pose}, CAM, {G: prior}, {G: (2.5, 4.0, 2.0)}, one_view
    )
    p = pairs[(A, G)]
    kept = set(p["matches"][p["inliers"], 1].tolist())
    assert kept >= set(range(40))  # (nearly) every right match survives
    assert not kept & set(bad.tolist())  # no wrong one does
    r = poses[G]
    assert r["accepted"], r["reason"]
    assert np.linalg.norm(np.asarray(r["center"]) - ground_pose.center) < 0.1

    # a POS far from the truth (30 m): the pose is rejected (not used downstream), but the matches that
    # agree on one camera are still verified by it (verify_on_consensus), the wrong ones are not
    far = Pose.from_center(ground_pose.R.T, ground_pose.center + [30.0, 0, 0])
    pairs, _, poses, _ = transfer.reduce_views(
        [v], {A: aerial_cam}, {A: aerial_pose}, CAM, {G: far}, {G: (2.5, 4.0, 2.0)}, one_view
    )
    assert not poses[G]["accepted"] and "POS" in poses[G]["reason"] and poses[G]["consensus"]
    p = pairs[(A, G)]
    kept = set(p["matches"][p["inliers"], 1].tolist())
    assert kept >= set(range(40)) and not kept & set(bad.tolist())
    # without that, no match of a ground image without an accepted pose is kept
    pairs, _, poses, _ = transfer.reduce_views(
        [v], {A: aerial_cam}, {A: aerial_pose}, CAM, {G: far}, {G: (2.5, 4.0, 2.0)},
        {"pnp": {"verify_on_consensus": False, "min_other_view_inliers": 0}},
    )  # fmt: skip
    assert pairs[(A, G)]["inliers"].sum() == 0

    # the aerial check: a wrong aerial keypoint is rejected before the merge
    kps_bad = dict(kps)
    kps_bad[A] = kps[A].copy()
    kps_bad[A][:5] += 40.0
    v_bad = view(
        "V1",
        [lambda r: pair(r, A, rows), lambda r: pair(r, G, rows)],
        n_render=n,
        depth=depth,
        pose=render_pose,
        kps=kps_bad,
    )
    pairs, _, _, stats = transfer.reduce_views(
        [v_bad], {A: aerial_cam}, {A: aerial_pose}, CAM, {G: prior}, {G: (2.5, 4.0, 2.0)}
    )
    assert stats["aerial_rejected"]["aerial_reprojection"] == 5
    assert not set(pairs[(A, G)]["matches"][:, 0].tolist()) & set(range(5))


def test_the_pos_gate_is_joint():
    """A pose that passes each POS limit alone but is off in several ways at once (the small preset's
    G0003: 8.5 m, 1.6 m and 10.4 deg from a POS of 2.5 m / 4 m / 2 deg) is rejected; typical ones pass."""
    pc = transfer.default_conf["pnp"]
    std = (2.5, 4.0, 2.0)
    assert transfer.prior_chi2(8.5, 1.6, 10.4, std, pc) > pc["prior_chi2"]
    for dxy, dz, drot in ((3.7, 9.1, 2.1), (5.2, 3.5, 6.4), (2.3, 2.8, 1.9)):
        assert transfer.prior_chi2(dxy, dz, drot, std, pc) < pc["prior_chi2"]
    # the floors: a POS claiming 1 cm and 0.01 deg does not make every pose fail
    assert transfer.prior_chi2(2.0, 2.0, 3.0, (0.01, 0.01, 0.01), pc) < pc["prior_chi2"]


def test_a_clustered_consensus_verifies_matches_but_gives_no_pose():
    """Correspondences in a small patch of the image agree on one camera (consensus) but fix its pose
    poorly: the pose is not accepted (spread), yet it verifies the matches."""
    rng = np.random.default_rng(4)
    pose = look_at(np.array([0.0, 0.0, 1.6]), np.array([0.0, 20.0, 3.0]))
    kp = np.stack([rng.uniform(300, 340, 40), rng.uniform(220, 250, 40)], 1)  # 40 x 30 px of 640 x 480
    X = pose.unproject(CAM.K, kp, rng.uniform(18.0, 22.0, 40))
    r = transfer.estimate_ground_pose(kp, X, CAM, pose, (2.5, 4.0, 2.0), transfer.default_conf)
    assert not r.accepted and "cover" in r.reason
    assert r.consensus and r.num_inliers >= 38
    few = transfer.estimate_ground_pose(kp[:8], X[:8], CAM, pose, (2.5, 4.0, 2.0), transfer.default_conf)
    assert not few.accepted and not few.consensus
