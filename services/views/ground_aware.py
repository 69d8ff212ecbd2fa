"""The ground-aware planner: for every ground camera, views at several heights above it, behind it or on
the way to the aerial camera that sees its target most alike, looking at that target; occluded ones and
those that see too little of what the ground camera sees are dropped."""

from __future__ import annotations

import logging

import numpy as np

from services.geometry import horizontal, look_at, optical_axis, pitch_deg, scaled_camera
from services.views.scene import Scene
from services.views.specs import ViewSpec, aerial_candidates, assign_candidates, stem

logger = logging.getLogger("midview.viewpoints")


def ground_target(g: str, scene: Scene, conf: dict) -> tuple[np.ndarray, str]:
    """The ground camera's target: with conf["target"]["carve"] enabled, where its optical axis leaves
    the space the aerial cameras' depth carves free (Scene.carved_target); else its optical axis against
    the scene (its own depth probe, the sparse points, the terrain), else `look_ahead_m` ahead."""
    gc = conf["ground"]
    cam, pose = scene.ground_cameras[g], scene.ground_poses[g]
    T = scene.carved_target(cam, pose, conf["target"]["carve"], gc["min_target_m"], gc["max_target_m"])
    if T is not None:
        return T, "carved"
    T, how = scene.target(cam, pose, conf["target"], gc["min_target_m"], gc["max_target_m"])
    if T is None:
        T = pose.center + gc["look_ahead_m"] * optical_axis(pose)
        T[2] = max(T[2], scene.terrain_z)
        how = "look-ahead"
    return T, how


def surface_targets(g: str, scene: Scene, conf: dict) -> list[np.ndarray]:
    """Points of what ground camera g sees within [min_target_m, max_target_m] (Scene.seen_points), the
    nearest its principal point first: other targets for its views when every line of sight to the one
    on its principal ray is blocked. [] without a depth probe."""
    gc = conf["ground"]
    cam, pose = scene.ground_cameras[g], scene.ground_poses[g]
    return scene.seen_points(cam, pose, conf["target"]["probe_width"], gc["min_target_m"], gc["max_target_m"])


def ground_view_candidates(g: str, scene: Scene, conf: dict) -> list[ViewSpec]:
    """The placements of conf["ground"]["placements"] for ground image g, in order, occluded ones dropped
    and those that see less than min_covisible of the ground camera's surface too; when none is left,
    those, the most covisible first. When every placement's line of sight to the target on the ground
    camera's principal ray is blocked, the same with the other targets of surface_targets, in turn."""
    gc = conf["ground"]
    min_cov = float(gc["min_covisible"] or 0.0)
    surface = (
        scene.ground_surface(g, gc["covisibility_width"], 1.5 * gc["max_target_m"], gc["surface"])
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


# what each placement checks: "above_terrain", its centre at least 1 m above the terrain; "occlusion_probe",
# its line of sight to the target free in the scene's depth. "at" is the ground camera itself: it stands
# where the ground camera stands, whatever the terrain's height, and what hides its target along the ground
# camera's own line of sight is a floater of the 3DGS
PLACEMENT_RULES: dict[str, dict[str, bool]] = {
    "at": {"above_terrain": False, "occlusion_probe": False},
    "above": {"above_terrain": True, "occlusion_probe": True},
    "back": {"above_terrain": True, "occlusion_probe": True},
    "aerial": {"above_terrain": True, "occlusion_probe": True},
}


def _placement_center(
    placement: str, height: float, C_g: np.ndarray, back: np.ndarray, anchors: list[str], scene: Scene
) -> np.ndarray | None:
    """The centre of a placement `height` metres above ground camera centre C_g: "at" and "above"
    straight above it, "back" along the horizontal unit vector `back` by the height too (45 degrees),
    "aerial" on the segment to the first anchor aerial camera (None without one or below the height)."""
    if placement in ("at", "above"):
        return C_g + np.array([0.0, 0.0, height])
    if placement == "back":
        return C_g + height * back + np.array([0.0, 0.0, height])
    if placement == "aerial":
        if not anchors:
            return None
        A = scene.aerial_poses[anchors[0]].center
        dz = A[2] - C_g[2]
        return None if dz <= height else C_g + (height / dz) * (A - C_g)
    raise ValueError(f"unknown placement {placement!r} ({', '.join(PLACEMENT_RULES)})")


def _placements(
    g: str, T: np.ndarray, how: str, surface: np.ndarray | None, scene: Scene, conf: dict
) -> tuple[list[ViewSpec], list[tuple[float, ViewSpec]]]:
    """The unoccluded placements looking at target T: (those that see min_covisible of `surface` or
    unchecked, [(covisible fraction, view)] of those that see less)."""
    gc = conf["ground"]
    min_cov = float(gc["min_covisible"] or 0.0)
    cam_g, pose_g = scene.ground_cameras[g], scene.ground_poses[g]
    C_g = pose_g.center
    back = horizontal(C_g - T)
    if back is None:
        back = horizontal(-optical_axis(pose_g))
    if back is None:
        back = np.array([0.0, -1.0, 0.0])
    cam = scaled_camera(cam_g, gc["max_width"], gc["fov_scale"])
    # the aerial camera seeing T most like the ground camera does (oblique ones only)
    probe = ViewSpec("probe", "ground-aware", g, cam, look_at(C_g + [0, 0, 10.0], T), T)
    anchors = [n for _, n in aerial_candidates(probe, scene, {**conf["candidates"], "skip_nadir": True})]
    out, weak = [], []  # weak: unoccluded but below min_cov, (covisible fraction, view)
    for height, placement in gc["placements"]:
        C = _placement_center(placement, height, C_g, back, anchors, scene)
        if C is None or np.linalg.norm(T - C) < 2.0:
            continue
        rules = PLACEMENT_RULES[placement]
        if rules["above_terrain"] and C[2] < scene.terrain_z + 1.0:
            continue
        if rules["occlusion_probe"] and scene.occluded(C, T, cam, gc["occlusion_ratio"]):
            logger.debug("%s %s %.0f m: the target is occluded", g, placement, height)
            continue
        pose = look_at(C, T)
        cov = scene.covisible_fraction(surface, cam, pose, gc["covisibility_width"])
        view = ViewSpec(
            f"G-{stem(g)}-{placement}{int(round(height)):02d}",
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
            views.append(assign_candidates(v, scene, conf["candidates"]))
        if not cands:
            logger.warning("%s: no unoccluded intermediate view", g)
    return views
