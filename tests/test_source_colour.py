"""Views coloured from the full-resolution aerial images through a depth map
(services.views.source_colour), on an analytic scene: a textured ground plane photographed by two oblique
cameras. With the true depth the view equals the plane's texture seen from the view (a homography of
it); a nearer surface in a source's depth hides the point from that source; a point no source sees keeps
the fallback colour."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.colmap_model import Camera, Pose, write_model
from services.splat.render import look_at
from services.views.source_colour import SourceImages

TEX_PX_PER_M = 40.0  # the plane's texture: 40 px per metre over [-20, 20] m
TEX_HALF_M = 20.0


def _texture() -> np.ndarray:
    rng = np.random.default_rng(3)
    n = int(2 * TEX_HALF_M * TEX_PX_PER_M)
    noise = rng.integers(0, 255, (n // 8, n // 8, 3), dtype=np.uint8)
    tex = cv2.resize(noise, (n, n), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(tex, (0, 0), 1.2)


def _plane_homography(camera: Camera, pose: Pose) -> np.ndarray:
    """Texture pixel (OpenCV centres) -> image pixel (OpenCV centres) for the plane z = 0."""
    # texture (col, row) -> world (x, y): x = (col + 0.5) / s - h, y = h - (row + 0.5) / s
    s, h = TEX_PX_PER_M, TEX_HALF_M
    T = np.array([[1 / s, 0, 0.5 / s - h], [0, -1 / s, h - 0.5 / s], [0, 0, 1]])
    P = camera.K @ np.c_[pose.R, pose.t]  # world -> COLMAP pixels
    H = P[:, [0, 1, 3]] @ T
    shift = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])  # COLMAP pixels -> OpenCV centres
    return shift @ H


def _plane_depth(camera: Camera, pose: Pose) -> np.ndarray:
    """z-depth of the plane z = 0 at every pixel (0 where the ray misses it)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
    rays = pose.unproject(camera.K, uv, np.ones(len(uv))) - pose.center  # world ray per unit z-depth
    z = -pose.center[2] / rays[:, 2]
    z = np.where((rays[:, 2] < 0) & np.isfinite(z), z, 0.0)
    return z.reshape(camera.height, camera.width).astype(np.float32)


def _view(width: int, height: int) -> tuple[Camera, Pose]:
    """The view camera of the tests (`width` x `height`, 0.95 focal length per pixel of width)."""
    f = 0.95 * width
    cam = Camera("PINHOLE", width, height, [f, f, width / 2, height / 2])
    return cam, look_at(np.array([-2.0, -9.0, 12.0]), np.array([0.0, 0.0, 0.0]))


@pytest.fixture
def plane_survey(tmp_path):
    tex = _texture()
    cam = Camera("PINHOLE", 800, 600, [700.0, 700.0, 400.0, 300.0])
    poses = {
        "aerial/A.jpg": look_at(np.array([-6.0, -12.0, 30.0]), np.array([0.0, 0.0, 0.0])),
        "aerial/B.jpg": look_at(np.array([8.0, 10.0, 32.0]), np.array([1.0, 0.0, 0.0])),
    }
    for name, pose in poses.items():
        H = _plane_homography(cam, pose)
        img = cv2.warpPerspective(tex, H, (cam.width, cam.height), flags=cv2.INTER_LINEAR)
        (tmp_path / "images" / "aerial").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(tmp_path / "images" / name), img)
    write_model(tmp_path / "sparse", {"c": cam}, {n: ("c", p) for n, p in poses.items()})
    return tmp_path, tex, cam, poses


def test_a_view_coloured_through_the_true_depth_is_the_scene_seen_from_it(plane_survey):
    root, tex, cam, poses = plane_survey
    src = SourceImages(root / "sparse", root / "images")
    view_cam, view = _view(400, 300)
    depth = _plane_depth(view_cam, view)
    fallback = np.zeros((300, 400, 3), np.uint8)
    rgb, _, stats = src.colour(view_cam, view, depth, fallback, lambda c, p: _plane_depth(c, p))
    truth = cv2.warpPerspective(tex, _plane_homography(view_cam, view), (400, 300), flags=cv2.INTER_LINEAR)
    truth = cv2.cvtColor(truth, cv2.COLOR_BGR2RGB)  # the sources were written as BGR, the view is RGB
    inner = np.zeros((300, 400), bool)
    inner[20:-20, 20:-20] = True
    assert stats["source_fraction"] > 0.95 and stats["sources_used"] >= 1
    err = np.abs(rgb.astype(float) - truth.astype(float)).mean(axis=2)[inner]
    # the sources, resampled once more, agree with the direct warp to some grey levels (resampling twice
    # blurs the random texture), far better than the same warp shifted by 2 px: the colour is in place
    shifted = np.abs(rgb.astype(float) - np.roll(truth, 2, axis=1).astype(float)).mean(axis=2)[inner]
    assert np.median(err) < 10.0 and np.median(err) < 0.3 * np.median(shifted), (err, shifted)


def test_hidden_points_and_points_no_source_sees_keep_the_fallback(plane_survey):
    root, _, cam, poses = plane_survey
    src = SourceImages(root / "sparse", root / "images")
    view_cam, view = _view(200, 150)
    depth = _plane_depth(view_cam, view)
    fallback = np.full((150, 200, 3), 7, np.uint8)
    # every source's depth says a surface stands 5 m in front of the plane: nothing is visible
    occluded = lambda c, p: np.maximum(_plane_depth(c, p) - 5, 0)  # noqa: E731
    rgb, _, stats = src.colour(view_cam, view, depth, fallback, occluded)
    assert stats["source_fraction"] == 0.0 and (rgb == 7).all()
    # pixels without depth keep the fallback; the others take a source's colour
    depth[:, :100] = 0
    src2 = SourceImages(root / "sparse", root / "images")
    rgb, _, stats = src2.colour(view_cam, view, depth, fallback, lambda c, p: _plane_depth(c, p))
    assert (rgb[:, :100] == 7).all() and (rgb[:, 120:] != 7).any(axis=2).mean() > 0.9
    assert 0.4 < stats["source_fraction"] <= 0.5


def test_a_missing_source_image_is_a_clear_error(plane_survey):
    root, _, cam, _ = plane_survey
    (root / "images" / "aerial" / "A.jpg").unlink()
    (root / "images" / "aerial" / "B.jpg").unlink()
    src = SourceImages(root / "sparse", root / "images")
    view_cam, view = _view(200, 150)
    with pytest.raises(FileNotFoundError, match="A.jpg|B.jpg"):
        black = np.zeros((150, 200, 3), np.uint8)
        src.colour(view_cam, view, _plane_depth(view_cam, view), black, _plane_depth)


def test_points_the_sources_see_through_are_floaters(plane_survey):
    root, _, _, poses = plane_survey
    src = SourceImages(root / "sparse", root / "images")
    depth_fn = lambda c, p: _plane_depth(c, p)  # noqa: E731
    on_plane = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    in_the_air = np.array([[0.0, 0.0, 8.0], [1.0, 1.0, 5.0]])  # between the cameras and the plane
    below = np.array([[0.0, 0.0, -3.0]])  # hidden behind the plane: no evidence either way
    assert not src.seen_through(on_plane, depth_fn).any()
    assert src.seen_through(in_the_air, depth_fn).all()
    assert not src.seen_through(below, depth_fn).any()
    assert not src.seen_through(in_the_air, depth_fn, min_sources=3).any()  # only two sources here


def test_views_through_the_true_depth_are_coloured_from_the_aerial_images(tiny_survey):
    """The views' depth "truth" (bench only: a synthetic scene's): the view's depth is the scene's true
    depth and its colour comes from the aerial images through it: it follows the truth's own render of
    the view, with a black fallback colour. Without a scene it is a clear error."""
    from services.colmap_model import read_model
    from services.geometry import scaled_camera
    from services.splat.render import lowered_pose
    from services.views import GroundTruthRenderer, SourceRenderer

    class Black:
        name = "black"

        def render(self, camera, pose):
            h, w = camera.height, camera.width
            return np.zeros((h, w, 3), np.uint8), np.zeros((h, w), np.float32)

    sparse, images = tiny_survey / "gt" / "sparse", tiny_survey / "images"
    with pytest.raises(ValueError, match="synthetic scene"):
        SourceRenderer(Black(), sparse, images, {"depth": "truth"})
    renderer = SourceRenderer(Black(), sparse, images, {"depth": "truth"}, scene=tiny_survey)
    truth = GroundTruthRenderer(tiny_survey, sparse)
    cams, poses = read_model(sparse)
    for name in sorted(n for n in poses if n.startswith("aerial/"))[:3]:
        cam, pose = scaled_camera(cams[name], 320), lowered_pose(poses[name], 0.8, 0.0)
        rgb, depth = renderer.render(cam, pose)
        true_rgb, true_depth = truth.render(cam, pose)
        np.testing.assert_array_equal(depth, true_depth)
        seen = depth > 0
        assert seen.mean() > 0.5 and (rgb[seen] > 0).any(-1).mean() > 0.8  # not the black fallback
        assert np.corrcoef(rgb[seen].ravel(), true_rgb[seen].ravel())[0, 1] > 0.4


def test_a_view_across_the_plane_from_the_sources_takes_their_colour_through_its_normal(plane_survey):
    """A view 2 m over the plane, looking along it: source B sees the same points about 100 degrees off
    the view's rays (beyond max_angle_deg), but 20 degrees off the plane's normal. Through the depth map's
    normal B is admitted, so the two sources colour the view where both see the plane, in place; with the
    ray angle alone only A is, and the two-source consistency leaves the view to the fallback."""
    from services.views.source_colour import surface_normals

    root, tex, _, poses = plane_survey
    view_cam = Camera("PINHOLE", 200, 150, [190.0, 190.0, 100.0, 75.0])
    view = look_at(np.array([0.0, -30.0, 2.0]), np.array([0.0, 0.0, 0.0]))
    depth = _plane_depth(view_cam, view)
    normals = surface_normals(view_cam, view, depth, 0.01)
    known = np.isfinite(normals[..., 0])
    assert known[1:-1, 1:-1][depth[1:-1, 1:-1] > 0].mean() > 0.95 and not known[depth == 0].any()
    np.testing.assert_allclose(normals[known], np.tile([0.0, 0.0, 1.0], (known.sum(), 1)), atol=1e-4)
    fallback = np.zeros((150, 200, 3), np.uint8)
    depth_fn = lambda c, p: _plane_depth(c, p)  # noqa: E731
    by_ray = SourceImages(root / "sparse", root / "images", {"max_incidence_deg": None})
    ray_only = by_ray.colour(view_cam, view, depth, fallback, depth_fn)[2]["source_fraction"]
    src = SourceImages(root / "sparse", root / "images")
    rgb, _, stats = src.colour(view_cam, view, depth, fallback, depth_fn)
    # both sources see about a tenth of the view (the textured square's near part)
    assert stats["source_fraction"] > 0.05 and stats["source_fraction"] > 20 * ray_only
    assert stats["sources_used"] == 2
    truth = cv2.warpPerspective(tex, _plane_homography(view_cam, view), (200, 150), flags=cv2.INTER_LINEAR)
    truth = cv2.cvtColor(truth, cv2.COLOR_BGR2RGB)
    has = (rgb > 0).any(axis=2)
    err = np.abs(rgb.astype(float) - truth.astype(float)).mean(axis=2)[has]
    shifted = np.abs(rgb.astype(float) - np.roll(truth, 2, axis=1).astype(float)).mean(axis=2)[has]
    assert np.median(err) < 0.5 * np.median(shifted), (np.median(err), np.median(shifted))


@pytest.mark.parametrize("with_depth", [True, False])
@pytest.mark.parametrize("with_normal", [True, False])
def test_the_compiled_score_is_numpys(plane_survey, with_depth, with_normal):
    """A pinhole source's score over float32 points (one compiled pass) equals the NumPy pass's (float64
    points): the same points kept, their pixels, penalties and ground sampling; a nearer surface in the
    source's depth and the normals' incidence judged alike."""
    root, _, _, _ = plane_survey
    src = SourceImages(root / "sparse", root / "images", {"max_angle_deg": 25.0, "max_incidence_deg": 60.0})
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-25, 25, (20000, 2)), rng.uniform(-1, 6, 20000)]
    view = np.array([-2.0, -9.0, 12.0])
    ray_v = (X - view) / np.linalg.norm(X - view, axis=1, keepdims=True)
    normal = np.tile([0.0, 0.0, 1.0], (len(X), 1))
    normal[::7] = np.nan  # unknown normals
    depth_fn = (lambda c, p: np.clip(_plane_depth(c, p), 0, 30.0)) if with_depth else None
    n = normal if with_normal else None
    kept = 0
    for s in src.sources:
        assert s["pinhole"] is not None
        i64, uv64, pen64, gsd64 = src.score(s, X, ray_v, depth_fn, n)
        i32, uv32, pen32, gsd32 = src.score(s, X.astype(np.float32), ray_v.astype(np.float32), depth_fn, n)
        kept += len(i64)
        common, a, b = np.intersect1d(i64, i32, return_indices=True)
        assert len(common) >= 0.999 * max(len(i64), len(i32))  # float32 rounding at the borders only
        np.testing.assert_allclose(uv32[b], uv64[a], atol=0.02)
        np.testing.assert_allclose(pen32[b], pen64[a], atol=0.02)
        np.testing.assert_allclose(gsd32[b], gsd64[a], rtol=1e-4)
    assert 0 < kept < len(X)
