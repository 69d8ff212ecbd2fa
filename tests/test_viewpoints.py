"""Intermediate viewpoints (services/views/) on constructed cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services import views as vp
from services.colmap_model import Camera, Pose
from services.conf import merge_conf
from services.pos import ypr_to_matrix

CAM = Camera("PINHOLE", 800, 600, [700.0, 700.0, 400.0, 300.0])
GCAM = Camera("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0])


def pose_ypr(center, yaw, pitch, roll=0.0) -> Pose:
    return Pose.from_center(ypr_to_matrix(yaw, pitch, roll), np.asarray(center, float))


def principal_point_error(camera: Camera, pose: Pose, X: np.ndarray) -> float:
    uv, z = pose.project(camera.K, np.asarray(X, float)[None])
    assert z[0] > 0
    return float(np.linalg.norm(uv[0] - camera.K[:2, 2]))


@pytest.mark.parametrize("yaw", [0.0, 90.0, 213.0])
def test_paper_rule_oblique(yaw):
    # a 45 degree oblique 60 m above a target on the ground
    T = np.array([10.0, -5.0, 0.0])
    h = np.array([np.sin(np.radians(yaw)), np.cos(np.radians(yaw)), 0.0])
    pose_a = pose_ypr(T - 60.0 * h + [0, 0, 60.0], yaw, -45.0)
    assert principal_point_error(CAM, pose_a, T) < 1e-6
    pose_r, beta = vp.paper_viewpoint(pose_a, T, 0.5)
    C_a, C_r = pose_a.center, pose_r.center
    np.testing.assert_allclose(C_r[:2], C_a[:2], atol=1e-9)  # moved vertically only
    assert C_r[2] == pytest.approx(30.0)  # half the height above the target
    assert principal_point_error(CAM, pose_r, T) < 1e-6  # the target is on the principal ray again
    assert beta == pytest.approx(45.0 - np.degrees(np.arctan2(30.0, 60.0)), abs=1e-6)
    # a rotation about the camera's own x axis: x unchanged, the axis tilted up (towards the horizon)
    np.testing.assert_allclose(pose_r.R[0], pose_a.R[0], atol=1e-9)
    assert vp.pitch_deg(pose_r) > vp.pitch_deg(pose_a)
    assert vp.angle_deg(pose_r.R[2], pose_a.R[2]) == pytest.approx(beta, abs=1e-6)


def test_paper_rule_height_is_above_the_target():
    T = np.array([0.0, 0.0, 12.0])  # a roof 12 m up
    pose_a = pose_ypr([0.0, -40.0, 72.0], 0.0, -np.degrees(np.arctan2(60.0, 40.0)))
    pose_r, _ = vp.paper_viewpoint(pose_a, T, 0.5)
    assert pose_r.center[2] == pytest.approx(12.0 + 30.0)  # not half of 72 m
    assert principal_point_error(CAM, pose_r, T) < 1e-6


def test_paper_rule_nadir():
    T = np.array([3.0, 4.0, 0.0])
    pose_a = pose_ypr([3.0, 4.0, 80.0], 30.0, -90.0)
    pose_r, beta = vp.paper_viewpoint(pose_a, T, 0.5)
    assert beta == pytest.approx(0.0, abs=1e-9)
    assert pose_r.center[2] == pytest.approx(40.0)
    np.testing.assert_allclose(pose_r.R, pose_a.R, atol=1e-12)  # a lower nadir view
    assert principal_point_error(CAM, pose_r, T) < 1e-6


def test_paper_rule_rolled_camera_keeps_the_target_centred():
    T = np.array([0.0, 0.0, 0.0])
    pose_a = pose_ypr([0.0, -50.0, 50.0], 0.0, -45.0, roll=4.0)
    # its principal ray meets the ground somewhere near T: use that point as the target
    d = vp.optical_axis(pose_a)
    T = pose_a.center + d * (-pose_a.center[2] / d[2])
    pose_r, beta = vp.paper_viewpoint(pose_a, T, 0.5)
    assert principal_point_error(CAM, pose_r, T) < 1e-6
    assert 10.0 < beta < 25.0


def test_ray_target_points_takes_the_first_surface():
    C, d = np.zeros(3), np.array([0.0, 1.0, 0.0])
    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(-0.2, 0.2, 30), np.full(30, 20.0), rng.uniform(-0.2, 0.2, 30)]
    behind = np.c_[rng.uniform(-0.2, 0.2, 10), np.full(10, 35.0), rng.uniform(-0.2, 0.2, 10)]
    off_ray = np.c_[np.full(20, 5.0), np.full(20, 10.0), np.zeros(20)]
    t = vp.ray_target_points(C, d, np.concatenate([wall, behind, off_ray]))
    assert t == pytest.approx(20.0)
    assert vp.ray_target_points(C, d, off_ray) is None


def make_scene(ground_poses: dict[str, Pose]) -> vp.Scene:
    """Four 45-degree obliques and a nadir 60 m up around the origin; no sparse points; terrain z = 0."""
    aerial_poses = {}
    for k, yaw in enumerate((0.0, 90.0, 180.0, 270.0)):
        h = np.array([np.sin(np.radians(yaw)), np.cos(np.radians(yaw)), 0.0])
        aerial_poses[f"aerial/A{k + 1:04d}.jpg"] = pose_ypr(-60.0 * h + [0, 0, 60.0], yaw, -45.0)
    aerial_poses["aerial/A0005.jpg"] = pose_ypr([0.0, 0.0, 60.0], 0.0, -90.0)
    return vp.Scene(
        {n: CAM for n in aerial_poses},
        aerial_poses,
        {n: GCAM for n in ground_poses},
        ground_poses,
        {n: (2.5, 4.0, 2.0) for n in ground_poses},
        np.zeros((0, 3)),
        0.0,
    )


def test_ground_aware_planner():
    ground = {
        "ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 5.0),  # looking north at the origin
        "ground/G0002.jpg": pose_ypr([15.0, 2.0, 1.7], 270.0, 0.0),  # looking west
    }
    scene = make_scene(ground)
    conf = merge_conf(vp.confs["ground-aware"], {"views_per_ground_image": 3})
    views = vp.plan(scene, conf)
    assert views == sorted(views, key=lambda v: v.name)
    by_source = {g: [v for v in views if v.source == g] for g in ground}
    assert all(len(v) == 3 for v in by_source.values())
    z_aerial = max(p.center[2] for p in scene.aerial_poses.values())
    for v in views:
        assert v.planner == "ground-aware"
        # it looks at its target
        assert principal_point_error(v.camera, v.pose, v.target) < 1e-6
        # between the ground camera and the aerial cameras in height, at or above its ground camera
        z_g = ground[v.source].center[2]
        assert z_g - 1e-9 <= v.center[2] < z_aerial
        assert v.center[2] - z_g == pytest.approx(v.meta["height_m"])
        # its own ground image first among the candidates; oblique aerial candidates only
        assert v.ground[0] == v.source
        assert v.aerial and "aerial/A0005.jpg" not in v.aerial
        # the image x axis is level
        assert abs(v.pose.R[0, 2]) < 1e-9
    # the target is about `look_ahead_m` ahead of the ground camera (no points, no depth: look-ahead)
    v = by_source["ground/G0001.jpg"][0]
    assert np.linalg.norm(v.target - ground["ground/G0001.jpg"].center) == pytest.approx(15.0)
    # the north-looking ground camera is best served by the north-looking oblique (A0001)
    assert v.aerial[0] == "aerial/A0001.jpg"


def test_ground_aware_uses_the_depth_probe_and_skips_occluded_views():
    ground = {"ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)}
    scene = make_scene(ground)

    def depth_fn(camera: Camera, pose: Pose) -> np.ndarray:
        # a wall at y = 0 (north of the ground camera) and a roof over the camera (z = 8, y < -5)
        c, d = pose.center, pose.R[2]
        t_wall = (0.0 - c[1]) / d[1] if d[1] > 1e-9 else np.inf
        t_roof = (8.0 - c[2]) / d[2] if (c[2] > 8.0 and d[2] < 0) else np.inf
        hit_roof = np.isfinite(t_roof) and (c + t_roof * d)[1] < -5.0
        t = min(t_wall, t_roof if hit_roof else np.inf)
        z = t * (d @ d) if np.isfinite(t) else 0.0
        return np.full((camera.height, camera.width), z, np.float32)

    scene.depth_fn = depth_fn
    conf = merge_conf(vp.confs["ground-aware"], {"views_per_ground_image": 8})
    views = vp.plan(scene, conf)
    assert views
    for v in views:
        assert v.target[1] == pytest.approx(0.0, abs=1e-6)  # the target is on the wall
        assert v.meta["target_from"] == "depth"
        if v.center[2] > 8.0:  # nothing planned behind the roof
            c, d = v.center, v.target - v.center
            assert (c + (8.0 - c[2]) / d[2] * d)[1] >= -5.0
    assert {v.meta["placement"] for v in views} >= {"above"}


def test_paper_planner_selects_views_per_ground_image():
    ground = {"ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)}
    scene = make_scene(ground)
    conf = merge_conf(vp.confs["paper"], {"views_per_ground_image": 2})
    views = vp.plan(scene, conf)
    assert 1 <= len(views) <= 2
    for v in views:
        assert v.planner == "paper"
        assert "ground/G0001.jpg" in v.ground
        assert v.source in scene.aerial_poses and v.aerial[0] == v.source
        assert principal_point_error(v.camera, v.pose, v.target) < 1e-6
        assert v.center[2] == pytest.approx(30.0)  # half of 60 m above the terrain target


def test_paper_planner_extra_heights_and_per_planner_counts():
    ground = {"ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)}
    scene = make_scene(ground)
    over = {
        "views_per_ground_image": 1,
        "paper": {"extra_height_fractions": [0.25], "views_per_ground_image": 2},
        "ground": {"views_per_ground_image": 3},
    }
    views = vp.plan(scene, merge_conf(vp.confs["both"], over))
    paper = [v for v in views if v.planner == "paper"]
    assert sum(v.planner == "ground-aware" for v in views) == 3
    # the best aerial camera at both heights: the same target, on the principal ray at 30 m and 15 m
    assert len(paper) == 2 and paper[0].source == paper[1].source
    by_fraction = {v.meta["height_fraction"]: v for v in paper}
    assert by_fraction[0.5].name == "P-" + Path(paper[0].source).stem
    assert by_fraction[0.25].name == by_fraction[0.5].name + "-h25"
    assert by_fraction[0.5].center[2] == pytest.approx(30.0)
    assert by_fraction[0.25].center[2] == pytest.approx(15.0)
    np.testing.assert_allclose(by_fraction[0.25].target, by_fraction[0.5].target)
    for v in paper:
        assert principal_point_error(v.camera, v.pose, v.target) < 1e-6
        assert "ground/G0001.jpg" in v.ground


def test_views_json_round_trip(tmp_path):
    ground = {"ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)}
    views = vp.plan(make_scene(ground), vp.confs["both"])
    path = vp.write_views(tmp_path / "views.json", views, {"planner": "both"})
    back, doc = vp.read_views(path)
    assert doc["planner"] == "both"
    assert [v.name for v in back] == [v.name for v in views]
    for a, b in zip(views, back, strict=True):
        np.testing.assert_allclose(a.pose.R, b.pose.R)
        np.testing.assert_allclose(a.pose.t, b.pose.t)
        assert a.camera == b.camera and a.aerial == b.aerial and a.ground == b.ground
    assert {v.planner for v in views} == {"paper", "ground-aware"}


def test_viewpoint_overrides_take_lists_for_empty_ones():
    from services.conf import parse_overrides

    over = parse_overrides(["paper.extra_height_fractions=[0.3, 0.7]"], vp.confs["both"])
    assert over == {"paper": {"extra_height_fractions": [0.3, 0.7]}}
    with pytest.raises(ValueError, match="list"):
        parse_overrides(["paper.extra_height_fractions=0.3"], vp.confs["both"])
    with pytest.raises(ValueError, match="unknown key"):
        parse_overrides(["paper.height_fractions=[0.3]"], vp.confs["both"])


def raycast(camera: Camera, pose: Pose, hole: tuple[float, float, float] | None = None) -> np.ndarray:
    """Per-pixel z-depth of a scene of planes: the terrain (z = 0), a wall (y = 0, z <= 10) and, with
    `hole` (y, x, z) given, a screen across the street at that y with a 0.6 m square hole around (x, z)."""
    K = camera.K
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = d_cam @ pose.R  # world directions whose camera z is 1: the ray parameter is the z-depth
    c = pose.center
    depth = np.full(u.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -c[2] / d[..., 2]
        depth = np.where(t > 0, np.minimum(depth, t), depth)
        t = -c[1] / d[..., 1]
        z = c[2] + t * d[..., 2]
        depth = np.where((t > 0) & (z <= 10.0), np.minimum(depth, t), depth)
        if hole is not None:
            y_s, x_h, z_h = hole
            t = (y_s - c[1]) / d[..., 1]
            x, z = c[0] + t * d[..., 0], c[2] + t * d[..., 2]
            through = (np.abs(x - x_h) < 0.3) & (np.abs(z - z_h) < 0.3)
            depth = np.where((t > 0) & ~through, np.minimum(depth, t), depth)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def test_covisible_fraction_of_the_ground_cameras_surface():
    g = pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)  # looking north at the wall
    scene = make_scene({"ground/G0001.jpg": g})
    scene.depth_fn = raycast
    surface = scene.visible_surface(GCAM, g, 96, 60.0)
    assert surface is not None and len(surface) > 1000
    # on the terrain or the wall
    assert np.all((np.abs(surface[:, 2]) < 0.05) | (np.abs(surface[:, 1]) < 0.05))
    assert scene.covisible_fraction(surface, GCAM, g, 96) > 0.97
    assert scene.covisible_fraction(surface, GCAM, pose_ypr([0.0, -15.0, 1.6], 180.0, 0.0), 96) == 0.0
    behind_screen = pose_ypr([0.0, -25.0, 1.6], 0.0, 0.0)
    scene.depth_fn = lambda cam, pose: raycast(cam, pose, (-22.0, 40.0, 1.6))  # the hole out of sight
    assert scene.covisible_fraction(surface, GCAM, behind_screen, 96) == 0.0
    scene.depth_fn = lambda cam, pose: raycast(cam, pose, (-22.0, 0.0, 1.6))  # straight ahead
    assert 0.0 < scene.covisible_fraction(surface, GCAM, behind_screen, 96) < 0.2
    scene.depth_fn = None
    assert scene.visible_surface(GCAM, g, 96, 60.0) is None


def test_ground_aware_skips_views_that_see_little_of_what_the_ground_camera_sees():
    """A screen across the street behind the ground camera, with a hole where the line of sight of the
    view 10 m back and 10 m up passes: its target is not occluded, everything else the ground camera
    sees is."""
    g = pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)
    scene = make_scene({"ground/G0001.jpg": g})
    # back10: C = (0, -25, 11.6) looking at T = (0, 0, 1.6) crosses y = -22 at z = 10.4
    scene.depth_fn = lambda cam, pose: raycast(cam, pose, (-22.0, 0.0, 10.4))
    base = merge_conf(
        vp.confs["ground-aware"],
        {
            "views_per_ground_image": 8,
            "ground": {"placements": [[10.0, "back"], [5.0, "back"], [10.0, "above"]]},
        },
    )
    names = lambda conf: [v.name for v in vp.plan(scene, conf)]  # noqa: E731
    assert names(merge_conf(base, {"ground": {"min_covisible": 0.0}})) == [
        "G-G0001-above10",
        "G-G0001-back05",
        "G-G0001-back10",
    ]
    views = vp.plan(scene, base)
    assert [v.name for v in views] == ["G-G0001-above10", "G-G0001-back05"]
    assert all(v.meta["covisible"] >= 0.5 for v in views)
    # when no placement sees enough, the unoccluded ones are kept, the most covisible first
    seen = vp.ground_view_candidates(
        "ground/G0001.jpg", scene, merge_conf(base, {"ground": {"min_covisible": 1e-6}})
    )
    most = max(v.meta["covisible"] for v in seen)
    strict = merge_conf(base, {"ground": {"min_covisible": most + 0.01}})
    cands = vp.ground_view_candidates("ground/G0001.jpg", scene, strict)
    assert sorted(v.name for v in cands) == ["G-G0001-above10", "G-G0001-back05", "G-G0001-back10"]
    cov = [v.meta["covisible"] for v in cands]
    assert cov == sorted(cov, reverse=True) and cov[0] == most and cands[-1].name == "G-G0001-back10"
    assert [v.name for v in vp.plan(scene, merge_conf(strict, {"views_per_ground_image": 1}))] == [
        cands[0].name
    ]


def arcade_raycast(camera: Camera, pose: Pose) -> np.ndarray:
    """raycast's terrain and wall with an arcade roof over the street in front of the wall: z = 6,
    |x| <= 1, -25 <= y <= 0 (under it the wall at eye level; from above it hides that part of the wall)."""
    depth = raycast(camera, pose).astype(float)
    depth[depth == 0] = np.inf
    K = camera.K
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ pose.R
    c = pose.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (6.0 - c[2]) / d[..., 2]
        x, y = c[0] + t * d[..., 0], c[1] + t * d[..., 1]
        hit = (t > 0) & (np.abs(x) <= 1.0) & (y >= -25.0) & (y <= 0.0)
    depth = np.where(hit, np.minimum(depth, t), depth)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def test_ground_aware_views_look_at_another_point_when_the_target_is_hidden_from_above():
    """The ground camera looks under an arcade roof at the wall: every placement above it sees the roof,
    not that target. Its views then look at another point of what it sees (surface_targets), in view."""
    g = pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)  # looking north at the wall, the target under the roof
    scene = make_scene({"ground/G0001.jpg": g})
    # the default placements above the camera but aerial30, whose line of sight passes the roof 0.86 of
    # the way to the target: within occlusion_ratio 0.85 of it, not occluded ("at" sees under the roof)
    places = [
        p
        for p in vp.confs["ground-aware"]["ground"]["placements"]
        if p not in ([30.0, "aerial"], [0.0, "at"])
    ]
    conf = merge_conf(
        vp.confs["ground-aware"], {"views_per_ground_image": 2, "ground": {"placements": places}}
    )
    scene.depth_fn = raycast
    plain = vp.plan(scene, conf)
    assert plain and all(v.meta["target_from"] == "depth" for v in plain)
    assert all(np.allclose(v.target, [0.0, 0.0, 1.6], atol=0.2) for v in plain)
    scene.depth_fn = arcade_raycast
    T, how = vp.ground_target("ground/G0001.jpg", scene, conf)
    assert how == "depth" and np.allclose(T, [0.0, 0.0, 1.6], atol=0.2)
    views = vp.plan(scene, conf)
    assert len(views) == 2
    for v in views:
        assert v.meta["target_from"] == "surface"
        # on the wall, the street or the roof
        assert abs(v.target[1]) < 0.1 or abs(v.target[2]) < 0.1 or abs(v.target[2] - 6.0) < 0.1
        assert not scene.occluded(v.center, v.target, v.camera, conf["ground"]["occlusion_ratio"])
        assert principal_point_error(v.camera, v.pose, v.target) < 1e-6
        uv, z = g.project(GCAM.K, v.target[None])
        assert z[0] > 0 and 0 <= uv[0, 0] < GCAM.width and 0 <= uv[0, 1] < GCAM.height  # the camera sees it
    targets = vp.surface_targets("ground/G0001.jpg", scene, conf)
    assert len(targets) > 5 and np.allclose(targets[0], T, atol=0.2)  # the principal point's first
    scene.depth_fn = None
    assert vp.surface_targets("ground/G0001.jpg", scene, conf) == []


def test_a_view_at_the_ground_camera_sees_its_target_under_the_arcade():
    """Placement "at": the view stands at the ground camera's centre, even below the terrain's height plus
    a metre (a walker's camera on a street lower than the rest), and looks at its target: under the
    arcade's roof, which hides it from every placement above."""
    g = pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)
    scene = make_scene({"ground/G0001.jpg": g})
    scene.depth_fn = arcade_raycast
    conf = merge_conf(
        vp.confs["ground-aware"],
        {"views_per_ground_image": 1, "ground": {"placements": [[0.0, "at"], [10.0, "above"]]}},
    )
    (view,) = vp.plan(scene, conf)
    assert view.name == "G-G0001-at00" and view.meta["target_from"] == "depth"
    np.testing.assert_allclose(view.center, g.center, atol=1e-9)
    assert np.allclose(view.target, [0.0, 0.0, 1.6], atol=0.2) and view.meta["covisible"] > 0.95
    assert principal_point_error(view.camera, view.pose, view.target) < 1e-6
    # a surface the depth probe puts between the camera and its target (a CPU 3DGS's floater at the
    # street) hides it from every placement but "at", whose line of sight is the ground camera's own
    scene.occluded = lambda *a: True
    assert [v.name for v in vp.plan(scene, merge_conf(conf, {"views_per_ground_image": 2}))] == [
        "G-G0001-at00"
    ]
    scene.terrain_z = 1.0  # the camera 0.6 m above it: "at" stays, "above" (0 m) needs a metre
    both = merge_conf(
        conf, {"views_per_ground_image": 2, "ground": {"placements": [[0.0, "at"], [0.0, "above"]]}}
    )
    assert [v.name for v in vp.plan(scene, both)] == ["G-G0001-at00"]


def test_ground_aware_views_without_aerial_candidates():
    """The reducer's 3D links reach a view through the other views' aerial points: ground-aware views no
    aerial image is a candidate of are kept (unless keep_without_aerial is off)."""
    ground = {"ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 5.0)}
    scene = make_scene(ground)
    for n in [n for n in scene.aerial_poses if n != "aerial/A0005.jpg"]:  # the nadir camera only
        del scene.aerial_poses[n], scene.aerial_cameras[n]
    conf = merge_conf(vp.confs["ground-aware"], {"views_per_ground_image": 2})
    views = vp.plan(scene, conf)
    assert len(views) == 2 and all(v.aerial == [] and v.ground[0] == "ground/G0001.jpg" for v in views)
    assert vp.plan(scene, merge_conf(conf, {"ground": {"keep_without_aerial": False}})) == []


def _street_points(seed: int = 0) -> np.ndarray:
    """Sparse points of a street (z = 0, y < 0) and of a 10 m high wall along it (y = 0) with its roof."""
    rng = np.random.default_rng(seed)
    street = rng.uniform([-30, -30, -0.05], [30, 0, 0.05], (600, 3))
    wall = np.stack([rng.uniform(-30, 30, 300), np.zeros(300), rng.uniform(0, 10, 300)], 1)
    roof = rng.uniform([-30, 0, 9.95], [30, 10, 10.05], (200, 3))
    return np.concatenate([street, wall, roof])


def test_ground_cameras_are_placed_on_the_terrain():
    """GNSS heights are the noisiest part of a ground POS: each ground camera's height is fused with
    camera_height_m above the terrain under it (the low quantile of the sparse points around it: the
    street beside a wall, not its roof), weighted by the POS's std_z and terrain_std_m."""
    gc = vp.confs["both"]["ground"]
    ground = {
        "ground/G0001.jpg": pose_ypr([0.0, -15.0, -3.0], 0.0, 0.0),  # 3 m underground (std_z 4 m)
        "ground/G0002.jpg": pose_ypr([5.0, -2.0, 9.0], 0.0, 0.0),  # 9 m up, 2 m from the 10 m wall
        "ground/G0003.jpg": pose_ypr([-5.0, -20.0, 3.0], 0.0, 0.0),  # an RTK height (std_z 5 cm)
    }
    scene = make_scene(dict(ground))
    scene.points = _street_points()
    scene.ground_std["ground/G0003.jpg"] = (0.05, 0.05, 1.0)
    assert abs(vp.terrain_height(scene, np.array([5.0, -2.0]), gc)) < 0.05
    heights = vp.place_ground_on_terrain(scene, gc)
    assert heights == scene.ground_heights and set(heights) == set(ground)
    w_pos, w_ter = 1 / 4.0**2, 1 / gc["terrain_std_m"] ** 2
    for g, pos_z in (("ground/G0001.jpg", -3.0), ("ground/G0002.jpg", 9.0)):
        want = (w_pos * pos_z + w_ter * (heights[g]["terrain_z"] + gc["camera_height_m"])) / (w_pos + w_ter)
        assert scene.ground_poses[g].center[2] == pytest.approx(want, abs=1e-6)
        assert abs(scene.ground_poses[g].center[2] - gc["camera_height_m"]) < 0.2
        assert scene.ground_std[g][1] == pytest.approx((w_pos + w_ter) ** -0.5)
        # only the height moves: the position and the attitude are the POS's
        assert np.allclose(scene.ground_poses[g].center[:2], ground[g].center[:2])
        assert np.allclose(scene.ground_poses[g].R, ground[g].R)
    assert scene.ground_poses["ground/G0003.jpg"].center[2] == pytest.approx(3.0, abs=0.02)
    # the ground-aware views stand their height above the placed camera
    views = vp.plan(scene, merge_conf(vp.confs["ground-aware"], {"views_per_ground_image": 2}))
    assert views
    for v in (v for v in views if v.meta["placement"] == "above"):
        assert v.center[2] - scene.ground_poses[v.source].center[2] == pytest.approx(v.meta["height_m"])
    # too few points around a camera: its POS height stays
    scene = make_scene(dict(ground))
    scene.points = _street_points()[:20]
    assert vp.terrain_height(scene, np.array([0.0, -15.0]), gc) is None
    assert vp.place_ground_on_terrain(scene, gc) == {}
    assert scene.ground_poses["ground/G0001.jpg"].center[2] == -3.0


def test_the_scene_terrain_is_the_street_under_a_model_of_roofs():
    """The terrain height of the scene: the sparse points' low quantile, unless the ground cameras stand
    lower (an aerial model of a dense block may hold roofs and no street)."""
    ground = {f"ground/G{i:04d}.jpg": pose_ypr([5.0 * i, -15.0, 1.5 + 0.1 * i], 0.0, 0.0) for i in range(5)}
    street = _street_points()
    assert abs(vp.scene_terrain_z(street, ground, 1.5)) < 0.1
    roofs = street[street[:, 2] > 9.9]
    assert vp.scene_terrain_z(roofs, ground, 1.5) == pytest.approx(0.2)  # the cameras' median 1.7 - 1.5
    assert vp.scene_terrain_z(roofs, {}, 1.5) == pytest.approx(10.0, abs=0.1)
    assert vp.scene_terrain_z(np.zeros((0, 3)), {}, 1.5) == 0.0


def test_visible_points_are_the_nearest_sparse_points_in_view():
    """The ground camera's surface from the aerial model's sparse points: in its image and range, the
    nearest in each cell (the wall hides what is behind it)."""
    g = pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)  # looking north at the wall
    scene = make_scene({"ground/G0001.jpg": g})
    x, z = np.meshgrid(np.arange(-15, 15, 0.1), np.arange(0, 10, 0.1))
    wall = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], 1)  # dense: a point in every cell it covers
    behind = np.stack([np.linspace(-5, 5, 50), np.full(50, 5.0), np.full(50, 3.0)], 1)
    scene.points = np.concatenate([_street_points(), wall, behind])
    pts = scene.visible_points(GCAM, g, 96, 60.0)
    assert len(pts) > 250  # of the 24 x 18 cells of 4 px
    assert np.all(pts[:, 1] <= 0.05)  # the street and the wall: nothing behind the wall
    uv, z = g.project(GCAM.K, pts)
    assert np.all(z > 0) and np.all((uv >= 0).all(1) & (uv[:, 0] < GCAM.width) & (uv[:, 1] < GCAM.height))
    assert len(scene.visible_points(GCAM, pose_ypr([0.0, -15.0, 1.6], 180.0, 0.0), 96, 10.0)) < len(pts)
    # the covisibility of a placement with the exact depth agrees with the points' and the probe's surface
    scene.depth_fn = raycast
    pts = scene.ground_surface("ground/G0001.jpg", 96, 60.0, "points")
    assert scene.covisible_fraction(pts, GCAM, g, 96) > 0.9
    assert len(scene.ground_surface("ground/G0001.jpg", 96, 60.0, "depth")) > 1000


def test_paper_views_are_chosen_by_what_they_see_of_the_ground_cameras_surface():
    """paper.relevance "covisible": with a depth probe, the paper views that see most of what the ground
    camera sees (the aerial model's sparse points in its view) serve it."""
    g = pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)  # looking north at the wall (y = 0)
    scene = make_scene({"ground/G0001.jpg": g})
    x, z = np.meshgrid(np.arange(-15, 15, 0.25), np.arange(0, 10, 0.25))
    scene.points = np.concatenate([_street_points(), np.stack([x.ravel(), np.zeros(x.size), z.ravel()], 1)])
    scene.depth_fn = raycast
    conf = merge_conf(vp.confs["paper"], {"views_per_ground_image": 1})
    paper = vp.plan_paper(scene, conf)
    surface = scene.ground_surface("ground/G0001.jpg", 96, 60.0, "points")
    cov = {v.name: scene.covisible_fraction(surface, v.camera, v.pose, 96) for v in paper}
    # the oblique from the south sees all of it, those from the east and west a third (the wall at a
    # grazing angle, the street beside it)
    assert cov["P-A0001"] > 0.95 and cov["P-A0002"] < 0.5 and cov["P-A0004"] < 0.5
    (best,) = vp.select_paper(paper, scene, conf, 1)
    assert best.name == max(cov, key=cov.get) and "ground/G0001.jpg" in best.ground
    target = merge_conf(conf, {"paper": {"relevance": "target"}})
    assert [v.name for v in vp.select_paper(vp.plan_paper(scene, target), scene, target, 1)]
    with pytest.raises(ValueError, match="unknown paper.relevance"):
        vp.select_paper(paper, scene, merge_conf(conf, {"paper": {"relevance": "nearest"}}), 1)


def test_a_ground_cameras_target_is_where_the_aerial_cameras_stop_seeing_through():
    """services.views.scene.carve_ray: the ground camera's own depth probe sees a floater 2 m ahead (a
    CPU-trained 3DGS seen from the street); the aerial cameras' depth sees the street free up to the wall,
    and the target lands on the wall. With carving off (the default) the planner falls back to
    look-ahead."""
    from services.views.ground_aware import ground_target

    ground = {"ground/G0001.jpg": pose_ypr([0.0, -15.0, 1.6], 0.0, 0.0)}
    scene = make_scene(ground)

    def depth_fn(camera: Camera, pose: Pose) -> np.ndarray:
        if pose.center[2] < 5.0:  # the ground camera's probe: a floater
            return np.full((camera.height, camera.width), 2.0, np.float32)
        shifted = pose.center - np.array([0.0, 5.0, 0.0])  # raycast's wall moved to y = 5
        return raycast(camera, Pose(pose.R, -pose.R @ shifted))

    scene.depth_fn = depth_fn
    conf = merge_conf(vp.confs["ground-aware"], {"target": {"carve": {"enabled": True}}})
    T, how = ground_target("ground/G0001.jpg", scene, conf)
    assert how == "carved"
    assert T[1] == pytest.approx(5.0, abs=conf["target"]["carve"]["margin_m"] + 0.3)
    off = merge_conf(conf, {"target": {"carve": {"enabled": False}}})
    T, how = ground_target("ground/G0001.jpg", make_scene(ground), off)
    assert how == "look-ahead"


def test_a_ground_cameras_depth_probe_starts_past_a_floater_in_front_of_it():
    """A screen 1.5 m in front of a street-level camera (like the floaters a 3DGS trained on aerial
    images leaves there) hides the wall 25 m ahead from a probe at the camera; the probe that stands
    min_target_m ahead on the principal ray sees the wall (target.probe_from_min). Without it the planner
    falls back to look-ahead."""
    from services.views.ground_aware import ground_target

    g = "ground/G0001.jpg"
    scene = make_scene({g: pose_ypr([0.0, -25.0, 1.6], 0.0, 0.0)})
    scene.depth_fn = lambda camera, pose: raycast(camera, pose, hole=(-23.5, 50.0, 50.0))
    conf = merge_conf(vp.confs["ground-aware"], {"target": {"probe_from_min": True}})
    T, how = ground_target(g, scene, conf)
    assert how == "depth" and T[1] == pytest.approx(0.0, abs=0.1)
    T, how = ground_target(g, scene, merge_conf(conf, {"target": {"probe_from_min": False}}))
    assert how == "look-ahead" and T[1] == pytest.approx(-25.0 + conf["ground"]["look_ahead_m"], abs=0.1)
