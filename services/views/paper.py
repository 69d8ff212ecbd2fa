"""The paper's planner (section 3.2.2, equations 3-4): one view per aerial camera, lowered towards where
its principal ray meets the scene and turned to look at it again; then the views most relevant to each
ground image (covisibility through the depth probe, else heading and distance)."""

from __future__ import annotations

import logging
import math

import numpy as np

from services.colmap_model import Camera, Pose
from services.geometry import angle_deg, horizontal, pitch_deg, rot_x, scaled_camera
from services.views.scene import Scene
from services.views.specs import ViewSpec, assign_candidates, sees, stem

logger = logging.getLogger("midview.viewpoints")


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


def plan_paper(scene: Scene, conf: dict) -> list[ViewSpec]:
    """One view per aerial camera and height fraction (equations 3-4); their candidates are assigned."""
    pc = conf["paper"]
    fractions = [float(pc["height_fraction"])] + [float(f) for f in pc.get("extra_height_fractions") or []]
    views = []
    for a in sorted(scene.aerial_poses):
        cam, pose = scene.aerial_cameras[a], scene.aerial_poses[a]
        T, how = scene.target(cam, pose, conf["target"])
        if T is None:
            logger.debug("%s: the principal ray meets nothing", a)
            continue
        if pose.center[2] - T[2] < 1.0:
            continue
        for i, fraction in enumerate(fractions):
            new_pose, beta = paper_viewpoint(pose, T, fraction)
            v = ViewSpec(
                f"P-{stem(a)}" + ("" if i == 0 else f"-h{round(100 * fraction):02d}"),
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
            views.append(assign_candidates(v, scene, conf["candidates"]))
    return views


def _heading_and_distance(view: ViewSpec, ground_center: np.ndarray) -> float:
    """The angle (degrees) between the horizontal directions from the view's target to the view and to
    the ground camera, plus half the ground camera's distance to the target (m)."""
    hv, hg = horizontal(view.center - view.target), horizontal(ground_center - view.target)
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
    if not sees(scene.ground_cameras[g], pose, view.target, cc["ground_margin"]):
        return None
    return _heading_and_distance(view, pose.center)


def _covisible_scores(views: list[ViewSpec], g: str, scene: Scene, conf: dict, probes: dict) -> list | None:
    """(-covisible fraction, heading and distance term, name) of the views that see at least
    paper.min_covisible of what ground image g sees; None without a depth probe. `probes`: the views'
    depth probes, filled as they are made."""
    width = conf["ground"]["covisibility_width"]
    max_dist = conf["candidates"]["max_ground_distance_m"]
    pose_g = scene.ground_poses[g]
    surface = scene.ground_surface(g, width, max_dist, conf["paper"]["surface"]) if scene.depth_fn else None
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
