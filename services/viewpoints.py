"""Intermediate viewpoints between the aerial and the ground cameras (`views.json`).

Two planners, in the frame of the aerial model (local ENU, metres, z up; poses are cam_from_world,
docs/formats.md):

- **paper** (section 3.2.2, equations 3-4): for every aerial camera {R_a, C_a}, the ground target T is
  where its principal ray meets the scene. The camera is lowered vertically to `height_fraction` of its
  height above T, C_r = (X_a, Y_a, Z_T + (Z_a - Z_T) / 2), and turned about its own x axis by the angle
  beta between C_a->T and C_r->T so that T is again on its principal ray. In our convention
  (R_world_from_cam = R_a^T, turned about the camera x axis): R_world_from_cam_r = R_a^T @ Rx(theta),
  i.e. cam_from_world R_r = Rx(-theta) @ R_a, with |theta| = beta; theta > 0 tilts the optical axis
  upwards (towards the horizon) for a camera with a level x axis. A nadir camera gives beta = 0: a
  lower nadir view.
- **ground-aware**: for every ground camera (POS: noisy position and attitude), its target T (where its
  optical axis meets the scene, else a point `look_ahead_m` ahead), and views at several heights above
  the ground camera looking at T: straight above the ground camera, moved back along its heading, or on
  the segment from the ground camera to the aerial camera that sees T most like it does. A ground
  camera's POS height (GNSS: metres of noise) is first fused with the terrain under it plus the camera's
  height above the street (`place_ground_on_terrain`).

Targets come from a depth callback (e.g. a rendered depth map of the 3DGS model) when one is given, else
from the aerial model's sparse points near the ray, else from the terrain plane.

Each view gets candidate aerial and ground images for matching, chosen by POS geometry: the target must
project into the image, the viewing directions towards the target must be alike (angle), nadir aerial
images are skipped for oblique views. `views_per_ground_image` views are kept per ground image (for the
paper planner: the paper views most relevant to it), and every aerial image that can see a ground
target is made a candidate of at least one view.

    from services import viewpoints
    path = viewpoints.main(viewpoints.confs["ground-aware"], "sfm/sparse", "scene/pos.csv",
                           "scene/cameras.json", "sfm/georef.json", "plan/views.json")
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera, Pose, read_cameras_json, read_model
from services.conf import merge_conf
from services.geometry import look_at, scaled_camera
from services.pos import LocalFrame, PosRecord, read_pos
from services.sfm.georef import read_georef_frame
from shared.logging import stage

logger = logging.getLogger("midview.viewpoints")

# depth_fn(camera, pose) -> z-depth map (H, W) float, 0 where nothing was hit
DepthFn = Callable[[Camera, Pose], np.ndarray]

_BASE: dict[str, Any] = {
    "planner": "both",  # paper | ground-aware | both (measured best: bench/method.py)
    "views_per_ground_image": 4,
    "target": {
        "ray_cone_deg": 1.5,  # sparse points within this angle of a ray count as on it
        "min_points": 3,
        "quantile": 0.25,  # of the distances of the points on the ray: the first surface, not what's behind
        "depth_window": 5,  # pixels (at the depth probe's size) around the principal point
        "probe_width": 160,  # depth probes are rendered this wide
    },
    "paper": {
        "height_fraction": 0.5,  # equation 3: half the height above the target
        "extra_height_fractions": [],  # more views per aerial camera at these fractions (named P-<stem>-hNN)
        "max_width": 1024,  # views keep the aerial camera's field of view at this width
        "views_per_ground_image": None,  # None: the conf's views_per_ground_image
        # which paper views serve a ground image best: "covisible" (with a depth probe: the larger the
        # fraction of what the ground camera sees that the view sees too, at least min_covisible),
        # "covisible-heading" (of those, the most alike in heading and distance) or "target" (the ground
        # camera sees the view's target; the heading and distance between them)
        "relevance": "covisible",
        "min_covisible": 0.05,
        "surface": "points",  # what the ground camera sees (see ground.surface)
    },
    "ground": {
        "look_ahead_m": 15.0,  # target when the optical axis meets nothing in [min_target_m, max_target_m]
        "min_target_m": 4.0,
        "max_target_m": 40.0,
        "camera_height_m": 1.5,  # ground cameras above the terrain
        # the ground cameras' heights from the terrain under them: GNSS heights are the noisiest part of a
        # POS (the synthetic presets': 4 m std, some cameras metres underground or in the air), a camera on
        # a walker or a car stands camera_height_m above the street. The terrain's height: the low quantile
        # of the aerial model's sparse points within terrain_radius_m (a CPU-trained 3DGS's depth seen from
        # above is metres too low there), fused with the POS height by their std (terrain_std_m)
        "height_from_terrain": True,
        "terrain_std_m": 0.5,
        "terrain_radius_m": 10.0,
        "terrain_quantile": 0.1,
        "terrain_min_points": 10,
        # (height above the ground camera in metres, placement), in order of preference: the first
        # `views_per_ground_image` that are not occluded are kept. Placements: "above" (straight above
        # the ground camera), "back" (moved back along its heading by the height: a 45 degree line),
        # "aerial" (on the segment to the aerial camera seeing the target most like the ground camera).
        "placements": [
            [10.0, "back"],
            [20.0, "aerial"],
            [5.0, "above"],
            [20.0, "above"],
            [10.0, "above"],
            [5.0, "back"],
            [10.0, "aerial"],
            [30.0, "aerial"],
        ],
        "max_width": 1024,  # views use the ground camera's intrinsics, scaled to at most this width
        "views_per_ground_image": None,  # None: the conf's views_per_ground_image
        "fov_scale": 1.0,  # > 1 widens the field of view (focal length divided by it)
        "occlusion_ratio": 0.85,  # occluded: the view's depth towards the target is below this x its distance
        # keep views that no aerial image is a candidate of: the reducer's "3d" links reach their render
        # keypoints through the aerial points of the other views (services.reduce)
        "keep_without_aerial": True,
        # with a depth probe: a view must see at least this fraction of the surface the ground camera sees
        # from its POS pose (probed `covisibility_width` pixels wide; 0: unchecked; when no placement does,
        # the unoccluded ones are kept, the most covisible first). That surface: "depth",
        # its own depth probe (a CPU-trained 3DGS seen from the street shows floaters near it), or
        # "points", the aerial model's sparse points it sees (nearest per 4 px: mostly the street near it,
        # which views from above do not see: few placements pass 0.5)
        "min_covisible": 0.5,
        "covisibility_width": 96,
        "surface": "depth",
    },
    "candidates": {
        "aerial": 4,  # candidate aerial images per view
        "ground": 2,  # candidate ground images per view
        "margin": 0.05,  # the target may project this fraction of the image size outside it
        "ground_margin": 0.15,  # larger for ground cameras (POS noise of metres)
        "max_angle_deg": 75.0,  # between the view's and the image's viewing directions towards the target
        "max_ground_distance_m": 60.0,
        "nadir_pitch_deg": -80.0,  # aerial images steeper than this are nadir
        "skip_nadir": True,  # for oblique views (nadir images share almost nothing with ground views)
        "cover_aerial": True,  # make every aerial image that can see a ground target a candidate somewhere
    },
    "seed": 0,
}


confs: dict[str, dict[str, Any]] = {
    "paper": merge_conf(_BASE, {"planner": "paper"}),
    "ground-aware": merge_conf(_BASE, {"planner": "ground-aware"}),
    "both": merge_conf(_BASE, {"planner": "both"}),
}


# -- geometry ------------------------------------------------------------------------------------
def rot_x(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def optical_axis(pose: Pose) -> np.ndarray:
    """Unit optical axis in the world frame."""
    return pose.R[2] / np.linalg.norm(pose.R[2])


def pitch_deg(pose: Pose) -> float:
    """Elevation of the optical axis (0 horizontal, -90 nadir)."""
    return float(np.degrees(np.arcsin(np.clip(optical_axis(pose)[2], -1.0, 1.0))))


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    u, v = np.asarray(u, float), np.asarray(v, float)
    c = float(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def paper_viewpoint(pose_a: Pose, target: np.ndarray, fraction: float = 0.5) -> tuple[Pose, float]:
    """Equations 3-4: the aerial camera lowered vertically to `fraction` of its height above the target
    and turned about its own x axis until the target is on its principal ray again.

    Returns the new pose and beta (degrees, >= 0), the angle between C_a->T and C_r->T. The rotation is
    R_world_from_cam_r = R_world_from_cam_a @ Rx(theta) with theta = atan2(-d_y, d_z), d the direction
    C_r->T in the old camera frame; for a camera whose x axis is level, d lies in its y-z plane and
    |theta| = beta. Otherwise (a rolled camera) the remaining small rotation that puts T exactly on the
    principal ray is applied too.
    """
    target = np.asarray(target, float)
    C_a = pose_a.center
    C_r = np.array([C_a[0], C_a[1], target[2] + fraction * (C_a[2] - target[2])])
    d = target - C_r
    if np.linalg.norm(d) < 1e-9:
        raise ValueError("the lowered camera coincides with its target")
    Rwc = pose_a.R.T
    d_c = Rwc.T @ (d / np.linalg.norm(d))  # direction to T in the old camera frame
    theta = math.atan2(-d_c[1], d_c[2])
    Rwc_r = Rwc @ rot_x(theta)
    # residual (zero for a camera with a level x axis): rotate the axis onto d exactly
    z_now = Rwc_r[:, 2]
    z_goal = d / np.linalg.norm(d)
    axis = np.cross(z_now, z_goal)
    s, c = float(np.linalg.norm(axis)), float(z_now @ z_goal)
    if s > 1e-12:
        k = axis / s
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        ang = math.atan2(s, c)
        Rwc_r = (np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K) @ Rwc_r
    beta = angle_deg(target - C_a, target - C_r)
    return Pose.from_center(Rwc_r, C_r), beta


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


# -- scene ---------------------------------------------------------------------------------------
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

    def target(
        self, camera: Camera, pose: Pose, conf: dict, min_dist: float = 0.0, max_dist: float = np.inf
    ) -> tuple[np.ndarray | None, str]:
        """Where the principal ray meets the scene: (T, method) or (None, "none")."""
        c, d = pose.center, optical_axis(pose)
        tc = conf["target"]
        probe = self.depth_probe(camera, pose, tc["probe_width"])  # a failed probe falls back to the points
        z = depth_at_center(probe[1], tc["depth_window"]) if probe is not None else None
        if z is not None and min_dist <= z <= max_dist:
            return c + z * d, "depth"
        t = ray_target_points(
            c, d, self.points, tc["ray_cone_deg"], tc["min_points"], tc["quantile"], min_dist, max_dist
        )
        if t is not None:
            return c + t * d, "points"
        t = ray_plane(c, d, self.terrain_z)
        if t is not None and min_dist <= t <= max_dist:
            return c + t * d, "terrain"
        return None, "none"

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

    def ground_surface(self, g: str, conf: dict, max_dist: float, kind: str) -> np.ndarray | None:
        """What ground camera g sees, for covisibility checks: `kind` "points" (visible_points) or
        "depth" (visible_surface: its depth probe), probed conf["ground"]["covisibility_width"] pixels
        wide; None when there is nothing."""
        width = conf["ground"]["covisibility_width"]
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


# -- views ---------------------------------------------------------------------------------------
@dataclass
class ViewSpec:
    """One planned intermediate view."""

    name: str
    planner: str
    source: str  # the aerial or ground image it was planned from
    camera: Camera
    pose: Pose
    target: np.ndarray
    aerial: list[str] = field(default_factory=list)  # candidate aerial images for matching
    ground: list[str] = field(default_factory=list)  # candidate ground images
    meta: dict = field(default_factory=dict)

    @property
    def center(self) -> np.ndarray:
        return self.pose.center

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "planner": self.planner,
            "source": self.source,
            "camera": {
                "model": self.camera.model,
                "width": int(self.camera.width),
                "height": int(self.camera.height),
                "params": [float(p) for p in self.camera.params],
            },
            "pose": {"R": np.asarray(self.pose.R).tolist(), "t": np.asarray(self.pose.t).tolist()},
            "center": [float(v) for v in self.center],
            "target": [float(v) for v in self.target],
            "aerial": list(self.aerial),
            "ground": list(self.ground),
            "meta": self.meta,
        }

    @classmethod
    def from_json(cls, d: dict) -> ViewSpec:
        return cls(
            d["name"],
            d.get("planner", ""),
            d.get("source", ""),
            Camera(**d["camera"]),
            Pose(np.asarray(d["pose"]["R"], float), np.asarray(d["pose"]["t"], float)),
            np.asarray(d["target"], float),
            list(d.get("aerial", [])),
            list(d.get("ground", [])),
            dict(d.get("meta", {})),
        )


def _sees(camera: Camera, pose: Pose, X: np.ndarray, margin: float) -> bool:
    uv, z = pose.project(camera.K, np.asarray(X, float)[None])
    mx, my = margin * camera.width, margin * camera.height
    return bool(z[0] > 0 and -mx <= uv[0, 0] <= camera.width + mx and -my <= uv[0, 1] <= camera.height + my)


def aerial_candidates(view: ViewSpec, scene: Scene, conf: dict) -> list[tuple[float, str]]:
    """(angle, aerial name) of the aerial images that see the view's target, most alike first."""
    cc = conf["candidates"]
    u_v = view.center - view.target
    nadir_view = pitch_deg(view.pose) < cc["nadir_pitch_deg"]
    out = []
    for a, pose in scene.aerial_poses.items():
        if cc["skip_nadir"] and not nadir_view and pitch_deg(pose) < cc["nadir_pitch_deg"]:
            continue
        if not _sees(scene.aerial_cameras[a], pose, view.target, cc["margin"]):
            continue
        ang = angle_deg(u_v, pose.center - view.target)
        if ang <= cc["max_angle_deg"]:
            out.append((ang, a))
    return sorted(out)


def ground_candidates(view: ViewSpec, scene: Scene, conf: dict) -> list[tuple[float, str]]:
    """(angle, ground name) of the ground images (POS) that see the view's target, most alike first."""
    cc = conf["candidates"]
    u_v = view.center - view.target
    out = []
    for g, pose in scene.ground_poses.items():
        if np.linalg.norm(pose.center - view.target) > cc["max_ground_distance_m"]:
            continue
        if not _sees(scene.ground_cameras[g], pose, view.target, cc["ground_margin"]):
            continue
        ang = angle_deg(u_v, pose.center - view.target)
        if ang <= cc["max_angle_deg"] + 15.0:  # ground cameras are far below any view
            out.append((ang, g))
    return sorted(out)


def assign_candidates(view: ViewSpec, scene: Scene, conf: dict) -> ViewSpec:
    """Fill the view's candidate lists (its own source image first)."""
    cc = conf["candidates"]
    a = [n for _, n in aerial_candidates(view, scene, conf)]
    g = [n for _, n in ground_candidates(view, scene, conf)]
    if view.source in scene.aerial_poses:
        a = [view.source] + [n for n in a if n != view.source]
    if view.source in scene.ground_poses:
        g = [view.source] + [n for n in g if n != view.source]
    view.aerial = a[: cc["aerial"]]
    view.ground = g[: cc["ground"]]
    return view


def _stem(name: str) -> str:
    return Path(name).stem


def plan_paper(scene: Scene, conf: dict) -> list[ViewSpec]:
    """One view per aerial camera and height fraction (equations 3-4); their candidates are assigned."""
    pc = conf["paper"]
    fractions = [float(pc["height_fraction"])] + [float(f) for f in pc.get("extra_height_fractions") or []]
    views = []
    for a in sorted(scene.aerial_poses):
        cam, pose = scene.aerial_cameras[a], scene.aerial_poses[a]
        T, how = scene.target(cam, pose, conf)
        if T is None:
            logger.debug("%s: the principal ray meets nothing", a)
            continue
        if pose.center[2] - T[2] < 1.0:
            continue
        for i, fraction in enumerate(fractions):
            new_pose, beta = paper_viewpoint(pose, T, fraction)
            v = ViewSpec(
                f"P-{_stem(a)}" + ("" if i == 0 else f"-h{round(100 * fraction):02d}"),
                "paper",
                a,
                scaled_camera(cam, pc["max_width"]),
                new_pose,
                T,
                meta={
                    "beta_deg": beta,
                    "target_from": how,
                    "pitch_deg": pitch_deg(new_pose),
                    "height_fraction": fraction,
                },
            )
            views.append(assign_candidates(v, scene, conf))
    return views


def ground_target(g: str, scene: Scene, conf: dict) -> tuple[np.ndarray, str]:
    """The ground camera's target: its optical axis against the scene, else `look_ahead_m` ahead."""
    gc = conf["ground"]
    cam, pose = scene.ground_cameras[g], scene.ground_poses[g]
    T, how = scene.target(cam, pose, conf, gc["min_target_m"], gc["max_target_m"])
    if T is None:
        T = pose.center + gc["look_ahead_m"] * optical_axis(pose)
        T[2] = max(T[2], scene.terrain_z)
        how = "look-ahead"
    return T, how


def _horizontal(v: np.ndarray) -> np.ndarray | None:
    h = np.array([v[0], v[1], 0.0])
    n = np.linalg.norm(h)
    return h / n if n > 1e-6 else None


def surface_targets(g: str, scene: Scene, conf: dict) -> list[np.ndarray]:
    """Points of what ground camera g sees (its depth probe at a grid of image positions, within
    [min_target_m, max_target_m]), the nearest its principal point first: other targets for its views
    when every line of sight to the one on its principal ray is blocked. [] without a depth probe."""
    gc = conf["ground"]
    cam, pose = scene.ground_cameras[g], scene.ground_poses[g]
    probe = scene.depth_probe(cam, pose, conf["target"]["probe_width"])
    if probe is None:
        return []
    pc, d = probe
    found = []
    for fy in (0.35, 0.5, 0.65):
        for fx in (0.15, 0.3, 0.5, 0.7, 0.85):
            u, v = int(fx * pc.width), int(fy * pc.height)
            z = depth_at(d, u, v, 5, min_valid_div=2)
            if z is not None and gc["min_target_m"] <= z <= gc["max_target_m"]:
                X = unproject(pc.K, pose, np.array([u]), np.array([v]), np.array([z]))[0]
                found.append((float(np.hypot(fx - 0.5, fy - 0.5)), X))
    return [X for _, X in sorted(found, key=lambda fX: fX[0])]


def ground_view_candidates(g: str, scene: Scene, conf: dict) -> list[ViewSpec]:
    """The placements of conf["ground"]["placements"] for ground image g, in order, occluded ones dropped
    and those that see less than min_covisible of the ground camera's surface too; when none is left,
    those, the most covisible first. When every placement's line of sight to the target on the ground
    camera's principal ray is blocked, the same with the other targets of surface_targets, in turn."""
    gc = conf["ground"]
    min_cov = float(gc["min_covisible"] or 0.0)
    surface = (
        scene.ground_surface(g, conf, 1.5 * gc["max_target_m"], gc["surface"])
        if min_cov > 0 and scene.depth_fn
        else None
    )
    T, how = ground_target(g, scene, conf)
    out, weak = _placements(g, T, how, surface, scene, conf)
    if not out and not weak:
        for T in surface_targets(g, scene, conf):
            out, weak = _placements(g, T, "surface", surface, scene, conf)
            if out or weak:
                logger.info(
                    "%s: every line of sight to its target is blocked; another point it sees serves", g
                )
                break
    if not out and weak:  # a view that sees part of the ground camera's surface beats none
        weak.sort(key=lambda cv: -cv[0])
        logger.info(
            "%s: no placement sees %.0f%% of what the ground camera sees; the best sees %.0f%% (%s)",
            g,
            100 * min_cov,
            100 * weak[0][0],
            weak[0][1].name,
        )
        return [v for _, v in weak]
    return out


def _placements(
    g: str, T: np.ndarray, how: str, surface: np.ndarray | None, scene: Scene, conf: dict
) -> tuple[list[ViewSpec], list[tuple[float, ViewSpec]]]:
    """The unoccluded placements looking at target T: (those that see min_covisible of `surface` or
    unchecked, [(covisible fraction, view)] of those that see less)."""
    gc = conf["ground"]
    min_cov = float(gc["min_covisible"] or 0.0)
    cam_g, pose_g = scene.ground_cameras[g], scene.ground_poses[g]
    C_g = pose_g.center
    back = _horizontal(C_g - T)
    if back is None:
        back = _horizontal(-optical_axis(pose_g))
    if back is None:
        back = np.array([0.0, -1.0, 0.0])
    cam = scaled_camera(cam_g, gc["max_width"], gc["fov_scale"])
    # the aerial camera seeing T most like the ground camera does (oblique ones only)
    probe = ViewSpec("probe", "ground-aware", g, cam, look_at(C_g + [0, 0, 10.0], T), T)
    anchors = [
        n for _, n in aerial_candidates(probe, scene, merge_conf(conf, {"candidates": {"skip_nadir": True}}))
    ]
    out, weak = [], []  # weak: unoccluded but below min_cov, (covisible fraction, view)
    for height, placement in gc["placements"]:
        if placement == "above":
            C = C_g + np.array([0.0, 0.0, height])
        elif placement == "back":
            C = C_g + height * back + np.array([0.0, 0.0, height])
        elif placement == "aerial":
            if not anchors:
                continue
            A = scene.aerial_poses[anchors[0]].center
            dz = A[2] - C_g[2]
            if dz <= height:
                continue
            C = C_g + (height / dz) * (A - C_g)
        else:
            raise ValueError(f"unknown placement {placement!r} (above, back, aerial)")
        if np.linalg.norm(T - C) < 2.0 or C[2] < scene.terrain_z + 1.0:
            continue
        if scene.occluded(C, T, cam, gc["occlusion_ratio"]):
            logger.debug("%s %s %.0f m: the target is occluded", g, placement, height)
            continue
        pose = look_at(C, T)
        cov = scene.covisible_fraction(surface, cam, pose, gc["covisibility_width"])
        view = ViewSpec(
            f"G-{_stem(g)}-{placement}{int(round(height)):02d}",
            "ground-aware",
            g,
            cam,
            pose,
            T,
            meta={
                "height_m": float(height),
                "placement": placement,
                "target_from": how,
                "pitch_deg": pitch_deg(pose),
                **({"covisible": cov} if cov is not None else {}),
                **({"anchor": anchors[0]} if placement == "aerial" else {}),
            },
        )
        if cov is not None and cov < min_cov:
            logger.debug(
                "%s %s %.0f m: sees %.0f%% of what the ground camera sees", g, placement, height, 100 * cov
            )
            weak.append((cov, view))
            continue
        out.append(view)
    return out, weak


def plan_ground_aware(scene: Scene, conf: dict, n_per_ground: int) -> list[ViewSpec]:
    views = []
    for g in sorted(scene.ground_poses):
        cands = ground_view_candidates(g, scene, conf)
        for v in cands[:n_per_ground]:
            views.append(assign_candidates(v, scene, conf))
        if not cands:
            logger.warning("%s: no unoccluded intermediate view", g)
    return views


def _heading_and_distance(view: ViewSpec, ground_center: np.ndarray) -> float:
    """The angle (degrees) between the horizontal directions from the view's target to the view and to
    the ground camera, plus half the ground camera's distance to the target (m)."""
    hv, hg = _horizontal(view.center - view.target), _horizontal(ground_center - view.target)
    heading = angle_deg(hv, hg) if hv is not None and hg is not None else 90.0
    return heading + 0.5 * float(np.linalg.norm(ground_center - view.target))


def _relevance(view: ViewSpec, g: str, scene: Scene, conf: dict) -> float | None:
    """How well a view suits ground image g: None if g cannot see its target, else the angle (degrees)
    between their viewing directions plus a distance term."""
    cc = conf["candidates"]
    pose = scene.ground_poses[g]
    dist = float(np.linalg.norm(pose.center - view.target))
    if dist > cc["max_ground_distance_m"]:
        return None
    if not _sees(scene.ground_cameras[g], pose, view.target, cc["ground_margin"]):
        return None
    return _heading_and_distance(view, pose.center)


def _covisible_scores(views: list[ViewSpec], g: str, scene: Scene, conf: dict, probes: dict) -> list | None:
    """(-covisible fraction, heading and distance term, name) of the views that see at least
    paper.min_covisible of what ground image g sees; None without a depth probe. `probes`: the views'
    depth probes, filled as they are made."""
    width = conf["ground"]["covisibility_width"]
    max_dist = conf["candidates"]["max_ground_distance_m"]
    pose_g = scene.ground_poses[g]
    surface = scene.ground_surface(g, conf, max_dist, conf["paper"]["surface"]) if scene.depth_fn else None
    if surface is None:
        return None
    out = []
    for v in views:
        if np.linalg.norm(pose_g.center - v.target) > 2 * max_dist:
            continue
        if v.name not in probes:
            probes[v.name] = scene.depth_probe(v.camera, v.pose, width)
        cov = scene.covisible_fraction(surface, v.camera, v.pose, width, probes[v.name])
        if cov is not None and cov >= conf["paper"]["min_covisible"]:
            alike = _heading_and_distance(v, pose_g.center)
            out.append(
                (-cov, alike, v.name) if conf["paper"]["relevance"] == "covisible" else (alike, -cov, v.name)
            )
    return sorted(out)


def select_paper(views: list[ViewSpec], scene: Scene, conf: dict, n_per_ground: int) -> list[ViewSpec]:
    """The paper views most relevant to each ground image (n per ground image, conf["paper"]["relevance"]),
    each made to include that ground image among its candidates."""
    keep: dict[str, ViewSpec] = {}
    by_name = {v.name: v for v in views}
    probes: dict[str, tuple[Camera, np.ndarray] | None] = {}
    for g in sorted(scene.ground_poses):
        scored = None
        if conf["paper"]["relevance"] in ("covisible", "covisible-heading"):
            scored = _covisible_scores(views, g, scene, conf, probes)
        elif conf["paper"]["relevance"] != "target":
            known = "covisible, covisible-heading, target"
            raise ValueError(f"unknown paper.relevance {conf['paper']['relevance']!r} ({known})")
        if scored is None:
            scored = sorted((s, v.name) for v in views if (s := _relevance(v, g, scene, conf)) is not None)
        for *_, name in scored[:n_per_ground]:
            v = keep.setdefault(name, by_name[name])
            if g not in v.ground:
                v.ground = [*v.ground, g]
    return [keep[k] for k in sorted(keep)]


def cover_aerial(views: list[ViewSpec], scene: Scene, conf: dict) -> int:
    """Make every oblique aerial image that sees some view target a candidate of at least one view
    (the view whose direction is closest to its own). Returns how many were added."""
    covered = {a for v in views for a in v.aerial}
    cc = conf["candidates"]
    added = 0
    for a in sorted(scene.aerial_poses):
        if a in covered:
            continue
        pose, cam = scene.aerial_poses[a], scene.aerial_cameras[a]
        if cc["skip_nadir"] and pitch_deg(pose) < cc["nadir_pitch_deg"]:
            continue
        best = None
        for v in views:
            if not _sees(cam, pose, v.target, cc["margin"]):
                continue
            ang = angle_deg(v.center - v.target, pose.center - v.target)
            if ang <= cc["max_angle_deg"] and (best is None or (ang, v.name) < best[:2]):
                best = (ang, v.name, v)
        if best is not None:
            best[2].aerial = [*best[2].aerial, a]
            covered.add(a)
            added += 1
    return added


def plan(scene: Scene, conf: dict) -> list[ViewSpec]:
    """The views of conf["planner"] (paper, ground-aware or both), sorted by name."""
    n = int(conf["views_per_ground_image"])
    n_paper = int(conf["paper"].get("views_per_ground_image") or n)
    n_ground = int(conf["ground"].get("views_per_ground_image") or n)
    planner = conf["planner"]
    views: list[ViewSpec] = []
    if planner in ("paper", "both"):
        views += select_paper(plan_paper(scene, conf), scene, conf, n_paper)
    if planner in ("ground-aware", "both"):
        views += plan_ground_aware(scene, conf, n_ground)
    if planner not in ("paper", "ground-aware", "both"):
        raise ValueError(f"unknown planner {planner!r} (paper, ground-aware, both)")
    keep_bare = bool(conf["ground"]["keep_without_aerial"])
    views = [v for v in views if v.ground and (v.aerial or (keep_bare and v.planner == "ground-aware"))]
    if conf["candidates"]["cover_aerial"]:
        added = cover_aerial(views, scene, conf)
        if added:
            logger.info("%d aerial images added as candidates so that each is covered", added)
    return sorted(views, key=lambda v: v.name)


# -- inputs --------------------------------------------------------------------------------------
def pos_in_frame(
    records: list[PosRecord], frame: LocalFrame, names: list[str] | None = None
) -> dict[str, tuple[Pose | None, np.ndarray, PosRecord]]:
    """{name: (pose or None without attitude, centre, record)} of POS records in a local frame."""
    recs = [r for r in records if names is None or r.name in set(names)]
    if not recs:
        return {}
    xyz = frame.from_wgs84(
        np.array([r.lat for r in recs]), np.array([r.lon for r in recs]), np.array([r.h for r in recs])
    ).reshape(-1, 3)
    out = {}
    for r, c in zip(recs, xyz, strict=True):
        pose = Pose.from_center(r.R_world_from_cam, c) if r.R_world_from_cam is not None else None
        out[r.name] = (pose, c, r)
    return out


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

    conf = merge_conf(_BASE, conf or {})
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


def write_views(path: str | Path, views: list[ViewSpec], extra: dict | None = None) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"version": 1, **(extra or {}), "views": [v.to_json() for v in views]}
    path.write_text(json.dumps(doc, indent=1))
    return path


def read_views(path: str | Path) -> tuple[list[ViewSpec], dict]:
    """The views of a views.json and the document (with its other keys)."""
    doc = json.loads(Path(path).read_text())
    return [ViewSpec.from_json(v) for v in doc["views"]], doc


def summary(views: list[ViewSpec], scene: Scene) -> dict:
    cover_g = {g for v in views for g in v.ground}
    cover_a = {a for v in views for a in v.aerial}
    return {
        "num_views": len(views),
        "by_planner": {p: sum(v.planner == p for v in views) for p in sorted({v.planner for v in views})},
        "ground_covered": f"{len(cover_g & set(scene.ground_poses))}/{len(scene.ground_poses)}",
        "aerial_covered": f"{len(cover_a)}/{len(scene.aerial_poses)}",
        "num_pairs": int(sum(len(v.aerial) + len(v.ground) for v in views)),
    }


class NoViews(ValueError):
    """The planner found no view to render."""


def main(
    conf: dict,
    sparse: str | Path,
    pos: str | Path | list[PosRecord],
    cameras: str | Path | dict[str, Camera],
    georef: str | Path | LocalFrame,
    out_path: str | Path,
    depth_fn: DepthFn | None = None,
) -> Path:
    """Plan the intermediate views and write them to `out_path` (views.json). Raises NoViews, writing
    nothing, when no view can be planned."""
    conf = merge_conf(_BASE, conf)
    with stage(f"viewpoints:{conf['planner']}", logger):
        scene = load_scene(sparse, pos, cameras, georef, depth_fn, conf)
        views = plan(scene, conf)
        info = summary(views, scene)
        if not views:
            raise NoViews(
                f"no intermediate view could be planned (planner {conf['planner']}, ground images covered "
                f"{info['ground_covered']}): the log's warnings say why for each ground image"
            )
        frame = georef if isinstance(georef, LocalFrame) else read_georef_frame(georef)
        write_views(
            out_path,
            views,
            {
                "planner": conf["planner"],
                "frame": {"type": "ENU", "lat0": frame.lat0, "lon0": frame.lon0, "h0": frame.h0},
                "terrain_z": scene.terrain_z,
                "ground_heights": scene.ground_heights,
                "summary": info,
                "conf": conf,
            },
        )
        logger.info(
            "%d views (%s); ground images covered %s, aerial %s; %d matching pairs -> %s",
            info["num_views"],
            ", ".join(f"{k} {v}" for k, v in info["by_planner"].items()),
            info["ground_covered"],
            info["aerial_covered"],
            info["num_pairs"],
            out_path,
        )
    return Path(out_path)
