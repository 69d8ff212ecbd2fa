"""The piecewise-planar proxy of the aerial model (services.views.proxy): planes found in noisy points
of a box building on a ground plane, their extent, ray casting with occlusion, and how the 3DGS's depth
is kept in front of them."""

from __future__ import annotations

import numpy as np
import pytest

from services.colmap_model import Camera
from services.splat.render import look_at
from services.views.proxy import PlaneProxy, combine, detect_planes

BOX = (np.array([-5.0, -4.0, 0.0]), np.array([5.0, 4.0, 8.0]))  # a 10 x 8 x 8 m building


def _box_scene(rng, noise=0.03, density=6.0) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) on a 40 x 40 m ground (outside the footprint), the box's roof and its four walls,
    `density` per square metre with Gaussian noise; and each point's face (0 ground, 1 roof, 2-5 walls)."""
    lo, hi = BOX

    def face(n_pts, f):
        return rng.uniform(0, 1, (n_pts, 2)), f

    pts, labels = [], []
    g = rng.uniform(-20, 20, (int(1600 * density / 4), 2))
    g = g[~((g[:, 0] > lo[0]) & (g[:, 0] < hi[0]) & (g[:, 1] > lo[1]) & (g[:, 1] < hi[1]))]
    pts.append(np.c_[g, np.zeros(len(g))])
    labels.append(np.zeros(len(g), int))
    sx, sy, sz = hi - lo
    faces = [
        (lambda a, b: np.c_[lo[0] + a * sx, lo[1] + b * sy, np.full(len(a), hi[2])], sx * sy),
        (lambda a, b: np.c_[np.full(len(a), lo[0]), lo[1] + a * sy, b * sz], sy * sz),
        (lambda a, b: np.c_[np.full(len(a), hi[0]), lo[1] + a * sy, b * sz], sy * sz),
        (lambda a, b: np.c_[lo[0] + a * sx, np.full(len(a), lo[1]), b * sz], sx * sz),
        (lambda a, b: np.c_[lo[0] + a * sx, np.full(len(a), hi[1]), b * sz], sx * sz),
    ]
    for i, (make, area) in enumerate(faces, start=1):
        ab = rng.uniform(0, 1, (int(area * density), 2))
        pts.append(make(ab[:, 0], ab[:, 1]))
        labels.append(np.full(len(ab), i))
    P = np.concatenate(pts)
    return P + rng.normal(0, noise, P.shape), np.concatenate(labels)


def _box_depth(camera: Camera, pose) -> np.ndarray:
    """The true z-depth of the box and the ground plane (ray against the six faces, nearest hit)."""
    H, W = camera.height, camera.width
    K = camera.K
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    d = rays.reshape(-1, 3) @ pose.R
    C = pose.center
    lo, hi = BOX
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - C) / d, (hi - C) / d
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        t_box = np.where((tmax >= tmin) & (tmin > 0), tmin, np.inf)
        t_ground = np.where(d[:, 2] < 0, -C[2] / d[:, 2], np.inf)
    t = np.minimum(t_box, t_ground)
    return np.where(np.isfinite(t), t, 0.0).reshape(H, W)


def test_the_planes_of_a_box_building_and_the_ground_are_found():
    rng = np.random.default_rng(0)
    P, face = _box_scene(rng)
    planes = detect_planes(P, {"inlier_m": 0.12})
    assert len(planes) >= 6
    normals = {0: [0, 0, 1], 1: [0, 0, 1], 2: [1, 0, 0], 3: [1, 0, 0], 4: [0, 1, 0], 5: [0, 1, 0]}
    for f, n_true in normals.items():
        # the plane holding most of this face's points has the face's normal and holds little else
        best = max(planes, key=lambda p: (face[p[1]] == f).sum())
        plane, inl = best
        assert abs(abs(plane[:3] @ n_true) - 1) < 2e-3, (f, plane)
        assert (face[inl] == f).sum() > 0.9 * (face == f).sum(), f
        assert (face[inl] == f).mean() > 0.9, f


def test_the_proxy_depth_is_the_scene_depth_where_the_planes_hold_points():
    rng = np.random.default_rng(1)
    P, _ = _box_scene(rng)
    proxy = PlaneProxy.from_points(P, {"inlier_m": 0.12})
    cam = Camera("PINHOLE", 320, 240, [260.0, 260.0, 160.0, 120.0])
    pose = look_at(np.array([-14.0, -18.0, 12.0]), np.array([0.0, 0.0, 3.0]))  # a low oblique view
    depth = proxy.depth(cam, pose)
    truth = _box_depth(cam, pose)
    seen = truth > 0
    # the ground beyond its points' extent is not hit; where both have depth they agree to centimetres,
    # the box occludes the ground behind it
    both = seen & (depth > 0)
    assert both.mean() > 0.6 * seen.mean()
    rel = np.abs(depth[both] - truth[both]) / truth[both]
    assert np.median(rel) < 0.005 and np.quantile(rel, 0.95) < 0.03, np.quantile(rel, [0.5, 0.95])


def test_a_plane_without_points_there_is_not_hit():
    rng = np.random.default_rng(2)
    g = np.c_[rng.uniform(0, 10, (600, 2)), rng.normal(0, 0.02, 600)]  # ground points on [0, 10]^2 only
    proxy = PlaneProxy.from_points(g)
    assert len(proxy.planes) == 1
    cam = Camera("PINHOLE", 200, 200, [200.0, 200.0, 100.0, 100.0])
    over = proxy.depth(cam, look_at(np.array([5.0, 5.0, 20.0]), np.array([5.0, 5.01, 0.0])))
    away = proxy.depth(cam, look_at(np.array([60.0, 60.0, 20.0]), np.array([60.0, 60.01, 0.0])))
    assert (over[80:120, 80:120] == pytest.approx(20.0, abs=0.1)) and (away == 0).all()


def test_the_3dgs_depth_is_kept_in_front_of_the_planes_and_where_none_is_hit():
    planes = np.array([[10.0, 10.0, 0.0, 10.0]], np.float32)
    splat = np.array([[9.5, 6.0, 7.0, 0.0]], np.float32)
    # a plane hit: the planes' depth (9.5 is near it), unless the 3DGS sees something 15% in front (6.0);
    # no plane: the 3DGS's (7.0); neither: 0
    assert combine(planes, splat, 0.15).tolist() == [[10.0, 6.0, 7.0, 10.0]]


def test_what_the_aerial_images_see_through_in_front_of_the_planes_is_dropped():
    rng = np.random.default_rng(4)
    g = np.c_[rng.uniform(-10, 10, (800, 2)), rng.normal(0, 0.02, 800)]  # the ground plane z = 0
    proxy = PlaneProxy.from_points(g)
    cam = Camera("PINHOLE", 64, 48, [100.0, 100.0, 32.0, 24.0])
    pose = look_at(np.array([0.0, -1.0, 20.0]), np.array([0.0, 0.0, 0.0]))
    planes = proxy.depth(cam, pose)
    assert (planes > 0).all()
    splat = planes.copy()
    splat[:, :32] = 5.0  # something 15 m above the ground in the view's left half
    kept = proxy.fuse(cam, pose, splat)  # no free-space test: the 3DGS's surface in front stays
    assert (kept[:, :32] == 5.0).all() and np.allclose(kept[:, 32:], planes[:, 32:])

    def air_below_10m(X: np.ndarray) -> np.ndarray:  # the aerial images see through what floats there
        return X[:, 2] > 10.0

    fused = proxy.fuse(cam, pose, splat, air_below_10m)
    assert np.allclose(fused, planes)  # the floater is gone: the ground behind it
    fused = proxy.fuse(cam, pose, splat, lambda X: np.zeros(len(X), bool))
    assert (fused[:, :32] == 5.0).all()  # an occluder the aerial images see stays
    sky = look_at(np.array([0.0, -1.0, 20.0]), np.array([0.0, 60.0, 22.0]))  # looking over the horizon
    assert (proxy.depth(cam, sky) == 0).all()
    floaters = np.full((48, 64), 3.0, np.float32)
    assert (proxy.fuse(cam, sky, floaters) == 3.0).all()  # no plane, no test: the 3DGS's depth
    assert (proxy.fuse(cam, sky, floaters, air_below_10m) == 0).all()  # no plane and seen through: none


def test_walls_whose_points_stop_above_the_street_are_continued_down_to_the_terrain():
    rng = np.random.default_rng(5)
    P, face = _box_scene(rng)
    upper = (face <= 1) | (P[:, 2] > 4.5)  # the aerial images hold the walls' upper halves only
    P = P[upper]
    cam = Camera("PINHOLE", 320, 240, [260.0, 260.0, 160.0, 120.0])
    pose = look_at(np.array([0.0, -16.0, 1.5]), np.array([0.0, -4.0, 2.0]))  # a ground camera at the wall
    truth = _box_depth(cam, pose)
    lower = np.zeros_like(truth, bool)
    v, u = np.nonzero(truth > 0)
    X = pose.unproject(cam.K, np.stack([u + 0.5, v + 0.5], 1), truth[v, u])
    lower[v, u] = (np.abs(X[:, 1] + 4.0) < 0.05) & (X[:, 2] < 4.0)  # the wall's lower half in the view
    assert lower.mean() > 0.1

    def rel_error(conf: dict) -> np.ndarray:
        depth = PlaneProxy.from_points(P, {"inlier_m": 0.12, **conf}).depth(cam, pose)
        return np.where(depth[lower] > 0, np.abs(depth[lower] - truth[lower]) / truth[lower], np.inf)

    # without: the lower wall is missing (the ground behind it, or nothing); with: within 1% of the truth
    assert np.mean(rel_error({}) < 0.01) < 0.3
    assert np.mean(rel_error({"walls_to_terrain": True}) < 0.01) > 0.97


def test_a_plane_is_a_connected_surface_not_a_slice_through_every_facade_at_one_height():
    """Six facades, each in a plane of its own, each with a balcony slab at 6 m: a plane may take every
    point within its tolerance anywhere (one horizontal plane then holds the balconies of several
    facades 20-50 m apart, a surface the proxy then fills between them), or, with connected_m, only the
    points connected to where its hypothesis was drawn: one piece of one facade."""
    rng = np.random.default_rng(6)
    points, labels = [], []
    for k in range(6):
        x0, y0 = 20.0 * (k % 3), 25.0 * (k // 3) + 3.0 * k
        ab = rng.uniform(0, 1, (100, 2))
        wall = np.c_[x0 + 10.0 * ab[:, 0], np.full(100, y0), 8.0 * ab[:, 1]]
        slab = np.c_[x0 + 10.0 * rng.uniform(0, 1, 40), y0 - 0.6 * rng.uniform(0, 1, 40), np.full(40, 6.0)]
        points += [wall, slab]
        labels.append(np.full(140, k))
    P = np.concatenate(points) + rng.normal(0, 0.02, (840, 3))
    face = np.concatenate(labels)

    def facades_per_plane(conf: dict) -> list[int]:
        planes = detect_planes(P, {"inlier_m": 0.1, **conf})
        return [int((np.bincount(face[inl], minlength=6) >= 5).sum()) for _, inl in planes]

    assert max(facades_per_plane({})) >= 3  # a slice through several facades
    spans = facades_per_plane({"connected_m": 2.5})
    assert max(spans) == 1 and len(spans) == 12  # each facade's wall and its balcony


def _box_walls(camera: Camera, pose) -> tuple[np.ndarray, np.ndarray]:
    """(the true z-depth (H, W) of the box scene, the pixels on the box's walls)."""
    truth = _box_depth(camera, pose)
    v, u = np.nonzero(truth > 0)
    X = pose.unproject(camera.K, np.stack([u + 0.5, v + 0.5], 1), truth[v, u])
    wall = np.zeros_like(truth, bool)
    wall[v, u] = (X[:, 2] > 0.05) & (X[:, 2] < BOX[1][2] - 0.05)
    return truth, wall


def test_walls_under_the_roofs_outline_where_the_facades_hold_no_points():
    """The sparse model holds the roof and the street but not one point of the walls (facades the
    aerial images see at grazing angles): with roof_walls, walls stand under the roof's outline, fitted
    to its outermost points, from the roof down to the terrain. Seen from the street, the two walls
    the outline runs straight along come within 1% of their true depth."""
    rng = np.random.default_rng(5)
    P, face = _box_scene(rng)
    P = P[face <= 1]  # the ground and the roof
    cam = Camera("PINHOLE", 320, 240, [260.0, 260.0, 160.0, 120.0])
    for centre, target in (((0.0, -16.0, 1.5), (0.0, -4.0, 2.0)), ((14.0, -14.0, 1.5), (5.0, -4.0, 3.0))):
        pose = look_at(np.array(centre), np.array(target))
        truth, wall = _box_walls(cam, pose)
        assert wall.mean() > 0.15

        def within_1pct(conf: dict, pose=pose, truth=truth, wall=wall) -> float:
            d = PlaneProxy.from_points(P, {"inlier_m": 0.12, **conf}).depth(cam, pose)
            return float(np.mean(np.abs(d[wall] - truth[wall]) < 0.01 * truth[wall]))

        assert within_1pct({}) < 0.05  # no wall: the ground behind, or nothing
        assert within_1pct({"roof_walls": True}) > 0.85, centre


def test_facades_without_sparse_points_get_planes_from_the_dense_points_given_beside():
    """The sparse model holds the ground and the roof only; the dense stereo points hold the walls: the
    proxy built from both finds the walls and gives the box's depth at a low oblique view."""
    import pycolmap

    rng = np.random.default_rng(4)
    P, face = _box_scene(rng)
    rec = pycolmap.Reconstruction()
    for x in P[face <= 1]:
        rec.add_point3D(x, pycolmap.Track(), np.zeros(3, np.uint8))
    conf = {"inlier_m": 0.12, "min_track_length": 0}
    cam = Camera("PINHOLE", 320, 240, [260.0, 260.0, 160.0, 120.0])
    pose = look_at(np.array([-14.0, -18.0, 2.0]), np.array([0.0, 0.0, 3.0]))  # from the street
    truth = _box_depth(cam, pose)
    sparse_only = PlaneProxy.from_model(rec, conf)
    assert not any(abs(p.n[2]) < 0.1 for p in sparse_only.planes)
    dense = P[face >= 2][::3]  # coarser than the sparse points, as a voxel grid of the surface is
    both = PlaneProxy.from_model(rec, conf, dense=dense)
    assert sum(abs(p.n[2]) < 0.1 for p in both.planes) >= 2  # the two walls this view sees, at least
    depth = both.depth(cam, pose)
    rel = np.abs(depth - truth) / np.maximum(truth, 1e-6)
    hit_box = truth < _ground_only(cam, pose) - 0.5  # the pixels where the box stands in front
    assert hit_box.sum() > 2000
    assert (rel[hit_box] < 0.01).mean() > 0.9, np.quantile(rel[hit_box], [0.5, 0.9])
    assert (sparse_only.depth(cam, pose)[hit_box] > 0).mean() < 0.5  # without them: the box's sides missing


def _ground_only(camera: Camera, pose) -> np.ndarray:
    """The z-depth of the ground plane alone (inf where the ray does not come down)."""
    K = camera.K
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    rays = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    d = rays.reshape(-1, 3) @ pose.R
    with np.errstate(divide="ignore"):
        t = np.where(d[:, 2] < 0, -pose.center[2] / d[:, 2], np.inf)
    return t.reshape(camera.height, camera.width)


def test_a_roof_with_a_low_structure_on_it_still_gets_its_walls():
    """What stands on a roof (ducts, a stair house: 1-2 m high) puts many points over it; the roof still
    gets walls under its outline (roof_clutter_m: 3 m by default), where a rule counting every point a
    metre above it took the roof for a canopy under a facade and gave it none."""
    rng = np.random.default_rng(5)
    P, face = _box_scene(rng)
    P = P[face <= 1]  # the ground and the roof
    top = BOX[1][2]  # a 4 x 3 x 2 m unit on it: points on its top and its sides' upper half
    a, b = rng.uniform(0, 1, (2, 300))
    unit = [np.c_[-2.0 + 4.0 * a, -1.5 + 3.0 * b, np.full(300, top + 2.0)]]
    unit += [np.c_[np.full(100, x), -1.5 + 3.0 * a[:100], top + 1.0 + b[:100]] for x in (-2.0, 2.0)]
    unit += [np.c_[-2.0 + 4.0 * a[:100], np.full(100, y), top + 1.0 + b[:100]] for y in (-1.5, 1.5)]
    P = np.concatenate([P, *unit])
    cam = Camera("PINHOLE", 320, 240, [260.0, 260.0, 160.0, 120.0])
    pose = look_at(np.array((0.0, -16.0, 1.5)), np.array((0.0, -4.0, 2.0)))
    truth, wall = _box_walls(cam, pose)

    def within_1pct(conf: dict) -> float:
        d = PlaneProxy.from_points(P, {"inlier_m": 0.12, "roof_walls": True, **conf}).depth(cam, pose)
        return float(np.mean(np.abs(d[wall] - truth[wall]) < 0.01 * truth[wall]))

    assert within_1pct({"roof_clutter_m": 1.0}) < 0.05
    assert within_1pct({}) > 0.85
