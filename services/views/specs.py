"""Planned views (`ViewSpec`), the aerial and ground images each is matched with, and views.json."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.colmap_model import Camera, Pose
from services.geometry import angle_deg, pitch_deg
from services.views.scene import Scene


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


def sees(camera: Camera, pose: Pose, X: np.ndarray, margin: float) -> bool:
    uv, z = pose.project(camera.K, np.asarray(X, float)[None])
    mx, my = margin * camera.width, margin * camera.height
    return bool(z[0] > 0 and -mx <= uv[0, 0] <= camera.width + mx and -my <= uv[0, 1] <= camera.height + my)


def aerial_candidates(view: ViewSpec, scene: Scene, cc: dict) -> list[tuple[float, str]]:
    """(angle, aerial name) of the aerial images that see the view's target, most alike first (`cc`: the
    planners' `candidates` conf)."""
    u_v = view.center - view.target
    nadir_view = pitch_deg(view.pose) < cc["nadir_pitch_deg"]
    out = []
    for a, pose in scene.aerial_poses.items():
        if cc["skip_nadir"] and not nadir_view and pitch_deg(pose) < cc["nadir_pitch_deg"]:
            continue
        if not sees(scene.aerial_cameras[a], pose, view.target, cc["margin"]):
            continue
        ang = angle_deg(u_v, pose.center - view.target)
        if ang <= cc["max_angle_deg"]:
            out.append((ang, a))
    return sorted(out)


def ground_candidates(view: ViewSpec, scene: Scene, cc: dict) -> list[tuple[float, str]]:
    """(angle, ground name) of the ground images (POS) that see the view's target, most alike first."""
    u_v = view.center - view.target
    out = []
    for g, pose in scene.ground_poses.items():
        if np.linalg.norm(pose.center - view.target) > cc["max_ground_distance_m"]:
            continue
        if not sees(scene.ground_cameras[g], pose, view.target, cc["ground_margin"]):
            continue
        ang = angle_deg(u_v, pose.center - view.target)
        if ang <= cc["max_angle_deg"] + 15.0:  # ground cameras are far below any view
            out.append((ang, g))
    return sorted(out)


def assign_candidates(view: ViewSpec, scene: Scene, cc: dict) -> ViewSpec:
    """Fill the view's candidate lists (its own source image first)."""
    a = [n for _, n in aerial_candidates(view, scene, cc)]
    g = [n for _, n in ground_candidates(view, scene, cc)]
    if view.source in scene.aerial_poses:
        a = [view.source] + [n for n in a if n != view.source]
    if view.source in scene.ground_poses:
        g = [view.source] + [n for n in g if n != view.source]
    view.aerial = a[: cc["aerial"]]
    view.ground = g[: cc["ground"]]
    return view


def cover_aerial(views: list[ViewSpec], scene: Scene, cc: dict) -> int:
    """Make every oblique aerial image that sees some view target a candidate of at least one view
    (the view whose direction is closest to its own; `cc`: the planners' `candidates` conf). Returns how
    many were added."""
    covered = {a for v in views for a in v.aerial}
    added = 0
    for a in sorted(scene.aerial_poses):
        if a in covered:
            continue
        pose, cam = scene.aerial_poses[a], scene.aerial_cameras[a]
        if cc["skip_nadir"] and pitch_deg(pose) < cc["nadir_pitch_deg"]:
            continue
        best = None
        for v in views:
            if not sees(cam, pose, v.target, cc["margin"]):
                continue
            ang = angle_deg(v.center - v.target, pose.center - v.target)
            if ang <= cc["max_angle_deg"] and (best is None or (ang, v.name) < best[:2]):
                best = (ang, v.name, v)
        if best is not None:
            best[2].aerial = [*best[2].aerial, a]
            covered.add(a)
            added += 1
    return added


def stem(name: str) -> str:
    return Path(name).stem


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
