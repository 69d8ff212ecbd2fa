"""The aerial images' dense stereo surface (services.views.stereo) on an analytic scene: a textured ground
plane with a raised textured platform, photographed by nadir cameras of two flight lines flown in
opposite directions (the images of one turned half a turn against the other's). The surface
ray cast at a view none of the images was taken from gives the true depth of both levels; pairs along
the optical axis (their epipole inside the image) are not matched."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from services.colmap_model import Camera, Pose
from services.splat.render import look_at
from services.views.stereo import StereoSurface, confs, pair_depth, stereo_pairs

PX_PER_M = 40.0
HALF_M = 30.0
PLATFORM = (-6.0, 6.0, -4.0, 4.0, 5.0)  # x0, x1, y0, y1, height (m)


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = int(2 * HALF_M * PX_PER_M)
    noise = rng.integers(0, 255, (n // 6, n // 6), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(noise, (n, n), interpolation=cv2.INTER_CUBIC), (0, 0), 1.0)


def _true_depth(camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """z-depth (H, W) of the scene and the world points (H, W, 3) each pixel sees."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
    ray = pose.unproject(camera.K, uv, np.ones(len(uv))) - pose.center  # per unit z-depth
    C = pose.center
    z = -C[2] / ray[:, 2]  # the ground
    x0, x1, y0, y1, h = PLATFORM
    zp = (h - C[2]) / ray[:, 2]
    P = C + zp[:, None] * ray
    on = (P[:, 0] >= x0) & (P[:, 0] <= x1) & (P[:, 1] >= y0) & (P[:, 1] <= y1)
    z = np.where(on, zp, z)
    X = C + z[:, None] * ray
    return z.reshape(camera.height, camera.width), X.reshape(camera.height, camera.width, 3)


def _image(camera: Camera, pose: Pose, textures: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    _, X = _true_depth(camera, pose)
    col = (X[..., 0] + HALF_M) * PX_PER_M - 0.5
    row = (HALF_M - X[..., 1]) * PX_PER_M - 0.5
    x0, x1, y0, y1, h = PLATFORM
    up = X[..., 2] > h / 2
    ground = cv2.remap(textures[0], col.astype(np.float32), row.astype(np.float32), cv2.INTER_LINEAR)
    top = cv2.remap(textures[1], col.astype(np.float32), row.astype(np.float32), cv2.INTER_LINEAR)
    return np.where(up, top, ground)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    root = tmp_path_factory.mktemp("stereo")
    cam = Camera("PINHOLE", 640, 480, [560.0, 560.0, 320.0, 240.0])
    textures = (_texture(1), _texture(2))
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam.to_pycolmap(1))
    poses = {}
    for i, (x, y) in enumerate([(-8, -6), (0, -6), (8, -6), (-8, 6), (0, 6), (8, 6)], start=1):
        C = np.array([x, y, 40.0])
        # the second flight line is flown the other way: its images are turned half a turn
        poses[i] = look_at(C, C + np.array([0.0, 0.01 if y < 0 else -0.01, -1.0]))
        name = f"aerial/A{i}.jpg"
        (root / "images" / "aerial").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "images" / name), _image(cam, poses[i], textures))
        img = pycolmap.Image(name=name, camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(poses[i].R), poses[i].t))
    # sparse points on both levels, observed where they project inside each image
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-14, 14, (400, 2)), np.zeros(400)]
    x0, x1, y0, y1, h = PLATFORM
    inside = (pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1)
    pts[inside, 2] = h
    obs: dict[int, list[tuple[np.ndarray, int]]] = {i: [] for i in poses}
    for k, X in enumerate(pts):
        for i, pose in poses.items():
            uv, z = pose.project(cam.K, X[None])
            if z[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height:
                obs[i].append((uv[0], k))
    elems: dict[int, list[tuple[int, int]]] = {k: [] for k in range(len(pts))}
    for i, lst in obs.items():
        rec.image(i).points2D = pycolmap.Point2DList([pycolmap.Point2D(uv) for uv, _ in lst])
        for j, (_, k) in enumerate(lst):
            elems[k].append((i, j))
    for k, X in enumerate(pts):
        if len(elems[k]) >= 2:
            track = pycolmap.Track()
            for i, j in elems[k]:
                track.add_element(i, j)
            rec.add_point3D(X, track, np.array([128, 128, 128], np.uint8))
    (root / "sparse").mkdir()
    rec.write(str(root / "sparse"))
    return root, cam


def test_pairs_have_sideways_baselines_and_turned_pairs_are_matched(survey):
    root, _ = survey
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    pairs = stereo_pairs(
        rec,
        {
            "pairs_per_image": 2,
            "min_shared": 20,
            "max_axis_angle_deg": 30.0,
            "max_epipole_cos": 0.35,
            "min_base_ratio": 0.05,
        },
    )
    assert pairs and all(n >= 20 for _, _, n in pairs)
    assert {i for a, b, _ in pairs for i in (a, b)} == set(rec.images)


def test_a_pair_across_the_flight_lines_turned_half_a_turn_gives_the_true_depth(survey):
    root, _ = survey
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    assert (
        rec.images[1].cam_from_world().rotation.matrix()[0]
        @ rec.images[4].cam_from_world().rotation.matrix()[0]
        < 0
    )
    depth, K, Rt = pair_depth(rec, 1, 4, root / "images", {**confs["default"], "width": 640})
    H, W = depth.shape
    cam = Camera("PINHOLE", W, H, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    truth, _ = _true_depth(cam, Pose(Rt[:, :3], Rt[:, 3]))
    ok = depth > 0
    assert ok.mean() > 0.3
    assert np.median(np.abs(depth[ok] - truth[ok]) / truth[ok]) < 0.01


def test_the_surface_gives_the_true_depth_at_a_new_view(survey):
    root, cam = survey
    surface = StereoSurface.build(
        root / "sparse", root / "images", {"width": 640, "voxel_m": 0.05, "sdf_trunc_m": 0.2}
    )
    view = Camera("PINHOLE", 320, 240, [280.0, 280.0, 160.0, 120.0])
    pose = look_at(np.array([-3.0, -14.0, 22.0]), np.array([0.0, 0.0, 2.0]))
    depth = surface.depth(view, pose)
    truth, X = _true_depth(view, pose)
    seen = (np.abs(X[..., 0]) < 10) & (np.abs(X[..., 1]) < 8)  # what all six images see
    rel = np.abs(depth - truth) / truth
    assert (depth[seen] > 0).mean() > 0.8
    assert np.median(rel[seen & (depth > 0)]) < 0.01
    top = seen & (X[..., 2] > 2.5)
    assert top.sum() > 1000 and np.median(rel[top & (depth > 0)]) < 0.01  # the platform, 5 m up
    # its points for the plane proxy: one per voxel, on the surface (the ground or the platform)
    pts = surface.points(0.5)
    assert 0 < len(pts) < len(surface.mesh.vertex.positions)
    assert len(np.unique(np.floor(pts / 0.5), axis=0)) == len(pts)
    on = (np.abs(pts[:, 2]) < 0.3) | (np.abs(pts[:, 2] - 5.0) < 0.3)
    assert on.mean() > 0.8, np.quantile(pts[:, 2], [0.1, 0.5, 0.9])
    # the walls' only: the flat ground and platform top (nearly all of this scene) are left out
    walls = surface.points(0.5, max_tilt_deg=20.0)
    assert len(walls) < 0.2 * len(pts)
