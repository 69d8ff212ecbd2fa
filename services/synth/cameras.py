"""Camera layouts: a 5-camera oblique UAV rig flying a serpentine grid, and a walker / mobile-mapping
path along the streets around the surveyed blocks. Poses follow docs/formats.md (COLMAP camera frame,
local ENU world); attitudes are built with the gimbal yaw/pitch/roll convention of services.pos."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.colmap_model import Camera, Pose
from services.pos import ypr_to_matrix

from .scene import Scene, block_sides


@dataclass
class View:
    """One image: name ("aerial/A0001.jpg"), set, true R_world_from_cam (3, 3) and centre (3,)."""

    name: str
    image_set: str
    R: np.ndarray
    C: np.ndarray
    kind: str = ""  # nadir / oblique-N ... / along / in / diag / out

    @property
    def pose(self) -> Pose:
        return Pose.from_center(self.R, self.C)


def pinhole(conf: dict) -> Camera:
    """PINHOLE camera of a set conf: width, height, f (px); principal point at the image centre."""
    w, h, f = int(conf["width"]), int(conf["height"]), float(conf["f"])
    return Camera("PINHOLE", w, h, [f, f, w / 2.0, h / 2.0])


def small_rotation(rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    """A random rotation exp([w]x), w ~ N(0, sigma^2 I) in radians per axis."""
    w = rng.normal(0.0, math.radians(sigma_deg), 3)
    a = float(np.linalg.norm(w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def aerial_views(conf: dict, scene: Scene, rng: np.random.Generator) -> list[View]:
    """Serpentine flight lines along north over the surveyed area; at each station a nadir camera and
    four obliques (pitch conf["pitch"], headings forward/right/back/left of the flight direction)."""
    cam = pinhole(conf)
    alt = conf["altitude"]
    f = cam.params[0]
    fwd, side = conf["overlap"]
    sp_fwd = (1 - fwd) * alt * cam.height / f  # the image top points along the flight line
    sp_side = (1 - side) * alt * cam.width / f
    x0, y0, x1, y1 = scene.surveyed
    if conf.get("grid"):
        nx, ny = conf["grid"]
    else:
        nx = max(1, math.ceil((x1 - x0 - alt * cam.width / f) / sp_side) + 1)
        ny = max(1, math.ceil((y1 - y0 - alt * cam.height / f) / sp_fwd) + 1)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    views: list[View] = []
    for i in range(nx):
        heading = 0.0 if i % 2 == 0 else 180.0
        js = range(ny) if i % 2 == 0 else range(ny - 1, -1, -1)
        for j in js:
            C = np.array([cx + (i - (nx - 1) / 2) * sp_side, cy + (j - (ny - 1) / 2) * sp_fwd, alt])
            C = C + rng.normal(0.0, conf["jitter_m"], 3)
            wobble = small_rotation(rng, conf["jitter_deg"])
            rig = [("nadir", ypr_to_matrix(heading, -90.0, 0.0))]
            for k in range(4):
                yaw = (heading + 90.0 * k) % 360.0
                rig.append(
                    (f"oblique-{'NESW'[int(round(yaw / 90.0)) % 4]}", ypr_to_matrix(yaw, conf["pitch"], 0.0))
                )
            for kind, R in rig:
                views.append(View(f"aerial/A{len(views) + 1:04d}.jpg", "aerial", wobble @ R, C.copy(), kind))
    return views


def ground_views(conf: dict, scene: Scene, rng: np.random.Generator) -> list[View]:
    """Cameras along the kerbs of the surveyed blocks (counter-clockwise), in the driving lanes or on the
    opposite sidewalk, looking along the street, at the block's facades, diagonally, or across.
    conf["layout"]: "spread" (the default: `count` cameras spread evenly around the blocks) or "walk"
    (a walker's sequence: `count` cameras `spacing_m` apart, one after the other, each at the same
    offset from the kerb give or take 0.5 m)."""
    road, sidewalk = float(scene.lay[4]), float(scene.lay[7])
    sides = [s for b in scene.blocks if b["surveyed"] for s in block_sides(b)]
    lengths = np.array([s[3] for s in sides])
    total = float(lengths.sum())
    n = int(conf["count"])
    kinds = list(conf["views"])
    probs = np.array([conf["views"][k] for k in kinds], float)
    views: list[View] = []
    walk = conf.get("layout", "spread") == "walk"
    if walk:
        step = float(conf["spacing_m"])
        s0 = rng.uniform(0, total)
        walk_off = rng.uniform(2.7, road - 2.7) if rng.random() < conf["p_lane"] else None
    else:
        s0 = rng.uniform(0, total / n)
    for k in range(n):
        if walk:
            s = (s0 + k * step + rng.uniform(-0.1, 0.1) * step) % total
        else:
            s = (s0 + k * total / n + rng.uniform(-0.15, 0.15) * total / n) % total
        si = int(np.searchsorted(np.cumsum(lengths), s, side="right"))
        start, tan, nrm, length = sides[si]
        along = s - float(np.cumsum(lengths)[si] - length)
        if walk:
            base = walk_off if walk_off is not None else road + sidewalk / 2
            off = base + rng.uniform(-0.5, 0.5)
        elif rng.random() < conf["p_lane"]:
            off = rng.uniform(2.7, road - 2.7)
        else:
            off = road + rng.uniform(0.8, sidewalk - 0.8)
        xy = start + along * tan - off * nrm
        kind = kinds[int(rng.choice(len(kinds), p=probs / probs.sum()))]
        sgn = 1.0 if rng.random() < 0.5 else -1.0
        if kind == "along":
            d, jit = sgn * tan, 15.0
        elif kind == "in":
            d, jit = nrm, 20.0
        elif kind == "diag":
            d, jit = (sgn * tan + nrm) / math.sqrt(2), 10.0
        else:  # "out": across the street at the neighbouring block
            d, jit = -nrm, 20.0
        yaw = math.degrees(math.atan2(d[0], d[1])) + rng.uniform(-jit, jit)
        pitch = rng.uniform(*conf["pitch"])
        roll = rng.normal(0.0, conf["roll_deg"])
        C = np.array([xy[0], xy[1], rng.uniform(*conf["height_m"])])
        R = ypr_to_matrix(yaw % 360.0, pitch, roll)
        views.append(View(f"ground/G{k + 1:04d}.jpg", "ground", R, C, kind))
    return views
