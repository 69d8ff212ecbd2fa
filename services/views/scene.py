"""What the view planners know of the scene: the aerial model's cameras, poses and points, the ground
cameras' POS poses in its frame (heights fused with the terrain under them), and an optional depth
probe (a renderer of the aerial 3DGS) for targets, occlusion and covisibility; with the read-outs of
rays and depth maps those queries rest on (a ray against the sparse points or a plane, a probe's depth
at a pixel, pixels back to world points, free space carved by the aerial cameras' depth).

The planners (`paper`, `ground_aware`) ask the scene, never its read-outs: the calls run one way,
planner -> scene -> read-outs."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.colmap_model import Camera, Pose, read_cameras_json, read_model
from services.conf import merge_conf
from services.geometry import look_at, optical_axis, pos_in_frame
from services.pos import LocalFrame, PosRecord, read_pos
from services.sfm import read_georef_frame
from services.views.confs import BASE

logger = logging.getLogger("midview.viewpoints")

# depth_fn(camera, pose) -> z-depth map (H, W) float, 0 where nothing was hit
DepthFn = Callable[[Camera, Pose], np.ndarray]


@dataclass
class Scene:
    """What the planners know: aerial model poses and points, ground POS poses (model frame), cameras."""

    aerial_cameras: dict[str, Camera]  # per image name
    aerial_poses: dict[str, Pose]
    ground_cameras: dict[str, Camera]
    ground_poses: dict[str, Pose]  # from the POS, in the aerial model's frame
    ground_std: dict[str, tuple[float, float, float]]  # std_xy (m), std_z (m), std_att (deg)
    points: np.ndarray  # (P, 3) sparse points of the aerial model
    terrain_z: float
    depth_fn: DepthFn | None = None
    ground_heights: dict[str, dict] = field(default_factory=dict)  # see place_ground_on_terrain
    _aerial_maps: dict[int, list] = field(default_factory=dict, repr=False)  # aerial_depth_maps' cache

    def target(
        self, camera: Camera, pose: Pose, tc: dict, min_dist: float = 0.0, max_dist: float = np.inf
    ) -> tuple[np.ndarray | None, str]:
        """Where the principal ray meets the scene beyond `min_dist`: (T, method) or (None, "none"), by
        the planners' `target` conf `tc`. With tc["probe_from_min"] the depth probe stands `min_dist`
        ahead on the ray, so that what lies nearer (a floater in front of a street-level camera) hides
        nothing beyond it."""
        c, d = pose.center, optical_axis(pose)
        start = float(min_dist) if tc["probe_from_min"] and np.isfinite(min_dist) else 0.0
        probe_pose = Pose.from_center(pose.R.T, c + start * d) if start > 0 else pose
        probe = self.depth_probe(camera, probe_pose, tc["probe_width"])  # a failed probe: the points
        z = depth_at_center(probe[1], tc["depth_window"]) if probe is not None else None
        if z is not None and min_dist <= start + z <= max_dist:
            return c + (start + z) * d, "depth"
        t = ray_target_points(
            c, d, self.points, tc["ray_cone_deg"], tc["min_points"], tc["quantile"], min_dist, max_dist
        )
        if t is not None:
            return c + t * d, "points"
        t = ray_plane(c, d, self.terrain_z)
        if t is not None and min_dist <= t <= max_dist:
            return c + t * d, "terrain"
        return None, "none"

    def aerial_depth_maps(self, width: int) -> list[tuple[np.ndarray, Pose, np.ndarray]]:
        """[(K, pose, z-depth)] of every aerial camera (depth probes `width` pixels wide, rendered once);
        [] without a depth probe."""
        if width not in self._aerial_maps:
            maps = []
            for a in sorted(self.aerial_poses):
                probe = self.depth_probe(self.aerial_cameras[a], self.aerial_poses[a], width)
                if probe is not None:
                    maps.append((probe[0].K, self.aerial_poses[a], probe[1]))
            self._aerial_maps[width] = maps
        return self._aerial_maps[width]

    def carved_target(
        self, camera: Camera, pose: Pose, cc: dict, min_dist: float, max_dist: float
    ) -> np.ndarray | None:
        """Where the principal ray leaves the free space the aerial cameras' depth carves (carve_ray,
        by the planners' `target.carve` conf `cc`); None without a depth probe or where it meets nothing."""
        maps = self.aerial_depth_maps(int(cc["width"])) if cc["enabled"] else []
        if not maps:
            return None
        c, d = pose.center, optical_axis(pose)
        args = (cc["step_m"], cc["margin_m"], cc["free_fraction"], cc["min_views"])
        t = carve_ray(c, d, maps, min_dist, max_dist, *args)
        return None if t is None else c + t * d

    def occluded(self, center: np.ndarray, target: np.ndarray, camera: Camera, ratio: float) -> bool:
        """Whether something lies between `center` and `target` (depth probe, else sparse points)."""
        dist = float(np.linalg.norm(target - center))
        probe = self.depth_probe(camera, look_at(center, target), 96)
        z = depth_at_center(probe[1], 3) if probe is not None else None
        if z is not None:
            return z < ratio * dist
        if len(self.points) == 0:
            return False
        d = (target - center) / dist
        v = self.points - center[None]
        t = v @ d
        r = np.linalg.norm(v - t[:, None] * d[None], axis=1)
        return int(((t > 0.5) & (t < ratio * dist) & (r < 0.75)).sum()) >= 3

    def depth_probe(self, camera: Camera, pose: Pose, width: int) -> tuple[Camera, np.ndarray] | None:
        """(probe camera, z-depth map) of the camera scaled to `width` pixels; None without a depth
        probe or when it fails."""
        if self.depth_fn is None:
            return None
        pc = probe_camera(camera, width)
        try:
            return pc, np.asarray(self.depth_fn(pc, pose), float)
        except Exception as e:
            logger.debug("depth probe failed: %s", e)
            return None

    def visible_surface(self, camera: Camera, pose: Pose, width: int, max_dist: float) -> np.ndarray | None:
        """(N, 3) world points of what the camera sees (depth probe `width` pixels wide, depths up to
        max_dist); None without a depth probe."""
        probe = self.depth_probe(camera, pose, width)
        if probe is None:
            return None
        pc, d = probe
        v, u = np.nonzero(np.isfinite(d) & (d > 0) & (d <= max_dist))
        return unproject(pc.K, pose, u, v, d[v, u])

    def seen_points(
        self, camera: Camera, pose: Pose, width: int, min_dist: float, max_dist: float
    ) -> list[np.ndarray]:
        """World points (3,) the camera's depth probe (`width` pixels wide) sees within [min_dist,
        max_dist] at a grid of 15 image positions, the nearest the principal point first; [] without a
        depth probe."""
        probe = self.depth_probe(camera, pose, width)
        if probe is None:
            return []
        pc, d = probe
        found = []
        for fy in (0.35, 0.5, 0.65):
            for fx in (0.15, 0.3, 0.5, 0.7, 0.85):
                u, v = int(fx * pc.width), int(fy * pc.height)
                z = depth_at(d, u, v, 5, min_valid_div=2)
                if z is not None and min_dist <= z <= max_dist:
                    X = unproject(pc.K, pose, np.array([u]), np.array([v]), np.array([z]))[0]
                    found.append((float(np.hypot(fx - 0.5, fy - 0.5)), X))
        return [X for _, X in sorted(found, key=lambda fX: fX[0])]

    def visible_points(
        self, camera: Camera, pose: Pose, width: int, max_dist: float, cell: int = 4
    ) -> np.ndarray:
        """(N, 3) sparse points of the aerial model the camera sees: in its image (scaled to `width`
        pixels), up to max_dist away, the nearest in each `cell` x `cell` pixels (those behind it hidden).
        The ground cameras' surface where a depth probe from their height is not to be trusted (a 3DGS
        trained on aerial images, seen from the street)."""
        pc = probe_camera(camera, width)
        if len(self.points) == 0:
            return np.zeros((0, 3))
        uv, z = pose.project(pc.K, self.points)
        inside = (
            (z > 0.5) & (z <= max_dist) & (uv >= 0).all(1) & (uv[:, 0] < pc.width) & (uv[:, 1] < pc.height)
        )
        idx = np.flatnonzero(inside)
        cells = (uv[idx] // cell).astype(np.int64)
        key = cells[:, 1] * (pc.width // cell + 1) + cells[:, 0]
        order = np.lexsort((z[idx], key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        return self.points[idx[order[first]]]

    def ground_surface(self, g: str, width: int, max_dist: float, kind: str) -> np.ndarray | None:
        """What ground camera g sees, for covisibility checks: `kind` "points" (visible_points) or
        "depth" (visible_surface: its depth probe), probed `width` pixels wide; None when there is
        nothing."""
        cam, pose = self.ground_cameras[g], self.ground_poses[g]
        if kind == "points":
            pts = self.visible_points(cam, pose, width, max_dist)
        elif kind == "depth":
            pts = self.visible_surface(cam, pose, width, max_dist)
        else:
            raise ValueError(f"unknown surface {kind!r} (points, depth)")
        return pts if pts is not None and len(pts) else None

    def covisible_fraction(
        self,
        points: np.ndarray,
        camera: Camera,
        pose: Pose,
        width: int,
        probe: tuple[Camera, np.ndarray] | None = None,
    ) -> float | None:
        """The fraction of `points` (N, 3) the camera sees: in its image and not hidden (its depth probe,
        or `probe` made by depth_probe, agrees with their depth within 5% + 0.5 m); None without a depth
        probe or points."""
        if points is None or len(points) == 0:
            return None
        probe = probe or self.depth_probe(camera, pose, width)
        if probe is None:
            return None
        pc, d = probe
        uv, z = pose.project(pc.K, points)
        ui, vi = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (z > 0) & (ui >= 0) & (ui < pc.width) & (vi >= 0) & (vi < pc.height)
        dz = d[vi[inside], ui[inside]]
        seen = np.isfinite(dz) & (np.abs(dz - z[inside]) <= 0.05 * z[inside] + 0.5)
        return float(seen.sum() / len(points))


def load_scene(
    sparse: str | Path,
    pos: str | Path | list[PosRecord],
    cameras: str | Path | dict[str, Camera],
    georef: str | Path | LocalFrame,
    depth_fn: DepthFn | None = None,
    conf: dict | None = None,
) -> Scene:
    """The planners' inputs: the aerial model, the ground POS in its frame, the ground camera."""
    import pycolmap

    conf = merge_conf(BASE, conf or {})
    cams_a, poses_a = read_model(sparse)
    cams_a = {n: c for n, c in cams_a.items() if n.split("/", 1)[0] == "aerial"}
    poses_a = {n: p for n, p in poses_a.items() if n in cams_a}
    rec = pycolmap.Reconstruction(str(sparse))
    points = np.array([p.xyz for _, p in sorted(rec.points3D.items())], float).reshape(-1, 3)
    frame = georef if isinstance(georef, LocalFrame) else read_georef_frame(georef)
    records = read_pos(pos) if isinstance(pos, str | Path) else list(pos)
    cameras = read_cameras_json(cameras) if isinstance(cameras, str | Path) else dict(cameras)
    ground = {n: v for n, v in pos_in_frame(records, frame).items() if n.split("/", 1)[0] == "ground"}
    if "ground" not in cameras:
        raise ValueError("cameras.json has no 'ground' camera")
    ground_poses, ground_std = {}, {}
    for n, (pose, _, r) in sorted(ground.items()):
        if pose is None:
            logger.warning("%s: the POS has no attitude; no views planned for it", n)
            continue
        ground_poses[n] = pose
        ground_std[n] = r.std_or_default()
    terrain = scene_terrain_z(points, ground_poses, conf["ground"]["camera_height_m"])
    scene = Scene(
        cams_a,
        poses_a,
        {n: cameras["ground"] for n in ground_poses},
        ground_poses,
        ground_std,
        points,
        terrain,
        depth_fn,
    )
    if conf["ground"]["height_from_terrain"]:
        place_ground_on_terrain(scene, conf["ground"])
    return scene


def scene_terrain_z(points: np.ndarray, ground_poses: dict[str, Pose], camera_height_m: float) -> float:
    """The scene's terrain height: a low quantile of the sparse points (N, 3) or the ground cameras' median
    height minus camera_height_m, the lower of the two (over a dense block the aerial model may hold
    roofs and no street); 0 without either."""
    z_pts = float(np.quantile(points[:, 2], 0.05)) if len(points) >= 20 else None
    z_cam = (
        float(np.median([p.center[2] for p in ground_poses.values()])) - camera_height_m
        if ground_poses
        else None
    )
    known = [z for z in (z_pts, z_cam) if z is not None]
    return min(known) if known else 0.0


def terrain_height(scene: Scene, xy: np.ndarray, gc: dict) -> float | None:
    """Height of the terrain at the horizontal position `xy`: the `terrain_quantile` of the heights of
    the sparse points within `terrain_radius_m` (the street, not the roofs and facades beside it); None
    with fewer than `terrain_min_points` there."""
    if len(scene.points) == 0:
        return None
    near = (
        np.linalg.norm(scene.points[:, :2] - np.asarray(xy, float)[None, :2], axis=1)
        <= gc["terrain_radius_m"]
    )
    if near.sum() < gc["terrain_min_points"]:
        return None
    return float(np.quantile(scene.points[near, 2], gc["terrain_quantile"]))


def place_ground_on_terrain(scene: Scene, gc: dict) -> dict[str, dict]:
    """Move each ground camera's POS height towards camera_height_m above the terrain under it: the two
    heights weighted by the inverse of their variances (the POS's std_z, terrain_std_m), which also
    becomes the camera's std_z. Updates `scene` and returns {name: heights} (also scene.ground_heights)."""
    out = {}
    for n, pose in sorted(scene.ground_poses.items()):
        C = pose.center
        ground = terrain_height(scene, C[:2], gc)
        if ground is None:
            continue
        s_xy, s_pos, s_att = scene.ground_std[n]
        s_ter = float(gc["terrain_std_m"])
        w_pos, w_ter = 1.0 / max(s_pos, 1e-6) ** 2, 1.0 / max(s_ter, 1e-6) ** 2
        z = (w_pos * C[2] + w_ter * (ground + gc["camera_height_m"])) / (w_pos + w_ter)
        scene.ground_poses[n] = Pose.from_center(pose.R.T, np.array([C[0], C[1], z]))
        scene.ground_std[n] = (s_xy, float((w_pos + w_ter) ** -0.5), s_att)
        out[n] = {"pos_z": float(C[2]), "terrain_z": ground, "z": float(z)}
    if out:
        moved = np.array([abs(d["z"] - d["pos_z"]) for d in out.values()])
        logger.info(
            "ground cameras placed %.1f m above the terrain: heights moved by %.2f m (median), %.2f m (max)",
            gc["camera_height_m"],
            float(np.median(moved)),
            float(moved.max()),
        )
    scene.ground_heights = out
    return out


# The read-outs of rays and depth maps the scene's queries rest on


def ray_target_points(
    center: np.ndarray,
    direction: np.ndarray,
    points: np.ndarray,
    cone_deg: float = 1.5,
    min_points: int = 3,
    quantile: float = 0.25,
    min_dist: float = 0.0,
    max_dist: float = np.inf,
) -> float | None:
    """Distance along a ray to the first surface, from the sparse points within `cone_deg` of it
    (a low quantile of their distances: points behind the surface are seen from other cameras)."""
    if points is None or len(points) == 0:
        return None
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    v = np.asarray(points, float) - np.asarray(center, float)[None]
    t = v @ d
    r = np.linalg.norm(v - t[:, None] * d[None], axis=1)
    on = (t > max(min_dist, 1e-6)) & (t <= max_dist) & (r <= np.tan(np.radians(cone_deg)) * t)
    if on.sum() < min_points:
        return None
    return float(np.quantile(t[on], quantile))


def ray_plane(center: np.ndarray, direction: np.ndarray, z: float) -> float | None:
    """Distance along a ray to the horizontal plane at height z (None if it does not meet it ahead)."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    if abs(d[2]) < 1e-9:
        return None
    t = (z - center[2]) / d[2]
    return float(t) if t > 0 else None


def probe_camera(camera: Camera, width: int) -> Camera:
    """The camera scaled to `width` pixels (same field of view), for cheap depth probes."""
    s = min(1.0, width / camera.width)
    w, h = max(8, round(camera.width * s)), max(6, round(camera.height * s))
    K = camera.K
    sx, sy = w / camera.width, h / camera.height
    return Camera("PINHOLE", w, h, [K[0, 0] * sx, K[1, 1] * sy, K[0, 2] * sx, K[1, 2] * sy])


def depth_at(depth: np.ndarray, u: int, v: int, window: int = 5, min_valid_div: int = 3) -> float | None:
    """Median valid depth in a `window` x `window` patch around pixel (u, v); None when fewer than
    1/min_valid_div of the patch is valid."""
    r = max(0, window // 2)
    patch = depth[max(0, v - r) : v + r + 1, max(0, u - r) : u + r + 1]
    good = patch[np.isfinite(patch) & (patch > 0)]
    return float(np.median(good)) if good.size >= max(1, patch.size // min_valid_div) else None


def depth_at_center(depth: np.ndarray, window: int = 5) -> float | None:
    """Median valid depth in a window around the image centre (the principal point, for centred K)."""
    h, w = depth.shape
    return depth_at(depth, w // 2, h // 2, window)


def unproject(K: np.ndarray, pose: Pose, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(N, 3) world points at z-depths `z` behind pixels (u, v) (their centres) of a camera (K, pose)."""
    x_cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
    return (x_cam - pose.t[None]) @ pose.R  # R^T (x - t)


def carve_ray(
    center: np.ndarray,
    direction: np.ndarray,
    depth_maps: list[tuple[np.ndarray, Pose, np.ndarray]],
    t_min: float,
    t_max: float,
    step: float,
    margin: float,
    free_fraction: float,
    min_views: int,
) -> float | None:
    """The first distance along the ray (center + t direction, t in [t_min, t_max) by `step`) where the
    scene is no longer free space: fewer than `free_fraction` of the depth maps [(K, cam_from_world pose,
    z-depth (H, W), 0 where nothing)] that see the point (at least `min_views`) see `margin` beyond it.
    The maps are the aerial cameras' renders, where a 3DGS trained on them is at its best; a ray from a
    ground camera meets the facade it looks at where they stop seeing through. None: it meets nothing."""
    ts = np.arange(t_min, t_max, step)
    P = center[None] + ts[:, None] * direction[None]
    n_view, n_free = np.zeros(len(ts)), np.zeros(len(ts))
    for K, pose, D in depth_maps:
        uv, z = pose.project(K, P)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 1e-6) & (u >= 0) & (v >= 0) & (u < D.shape[1]) & (v < D.shape[0])
        dd = np.zeros(len(ts))
        dd[ok] = D[v[ok], u[ok]]
        seen = ok & (dd > 0)
        n_view += seen
        n_free += seen & (z < dd - margin)
    hit = np.flatnonzero((n_view >= min_views) & (n_free < free_fraction * n_view))
    return float(ts[hit[0]]) if len(hit) else None
