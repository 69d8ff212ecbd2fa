"""A piecewise-planar proxy of the aerial model: the geometry that colours the views from the sources.

A 3DGS trained on the CPU gets the scene's depth at the intermediate views only roughly right (a median
error of 3-8%, worse on uniform roofs and on facades the aerial images see at grazing angles), and a view
coloured from the full-resolution aerial images through that depth shifts their texture. Streets, roofs
and facades are planes, and the aerial model's sparse points on them are accurate to centimetres. This
finds those planes (sequential RANSAC with local samples, each plane's extent an occupancy grid of its
points, every connected part filled to its convex hull) and ray casts them: the nearest occupied plane
along each pixel's ray. `fuse` keeps the 3DGS's depth where it sees something clearly in front of the
planes (trees, cars, lamp posts; not the floaters a CPU-trained 3DGS grows in the air, which the aerial
images see through), and where no plane is hit.

    proxy = PlaneProxy.from_model("sfm/sparse")
    depth = proxy.fuse(camera, pose, depth_3dgs)
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from services.colmap_model import Camera, Pose

logger = logging.getLogger("midview.views.proxy")

FreeSpace = Callable[[np.ndarray], np.ndarray]  # world points (N, 3) -> bool (N,): seen through

confs: dict[str, dict[str, Any]] = {
    "default": {
        "min_track_length": 3,  # sparse points seen by fewer images are left out
        "inlier_m": 0.15,  # a point within this distance of a plane is on it
        "sample_radius_m": 3.0,  # a hypothesis: a point and two others within this distance
        "min_inliers": 25,
        "max_planes": 400,
        "hypotheses": 300,  # per plane found
        # planes as connected surfaces: a hypothesis is scored by its inliers within support_radius_m of
        # its sample, and a plane keeps only the inliers connected to them (gaps under connected_m); 0:
        # every inlier anywhere, which lets a horizontal plane at one storey's height gather the points
        # of every facade at that height across the site (and a facade then has no plane)
        "connected_m": 0.0,
        "support_radius_m": 10.0,
        "max_misses": 5,  # the search ends after this many rounds of hypotheses in a row find no plane
        "cell_m": 1.0,  # the occupancy grid of a plane's points
        "close_cells": 5,  # holes of up to this many cells between its points are closed
        "occluder": 0.15,  # the 3DGS's depth wins where it is this much (relative) in front of the plane
        # ... and where the aerial images do not see through it (`fuse` with a free-space test): a
        # CPU-trained 3DGS grows floaters in the air near the low views; trees, cars and roofs the aerial
        # images see where they are
        "free_space_stride": 4,  # the test at every this-many-th pixel (the mask then filled between)
        # walls continued down to the terrain (buildings stand on the street: LoD1): the aerial images see
        # a facade's lower storeys at grazing angles, behind cars and trees, so its sparse points thin out
        # towards the street, where the ground cameras look. A vertical plane (normal within
        # wall_max_tilt_deg of horizontal) at least wall_min_width_m wide has each column of its grid filled
        # from its lowest occupied cell down to the terrain there (the terrain_quantile of the heights of
        # the points within terrain_radius_m), by at most wall_max_drop_m
        "walls_to_terrain": False,
        # walls under the roofs' outlines (LoD1: city buildings are vertical): every roof (a horizontal
        # plane at least roof_min_height_m above the terrain, roof_min_area_m2 large, nothing standing on
        # it) gets a vertical wall under each edge of its
        # outline (simplified to roof_outline_m) at least wall_min_width_m long, from the roof down to the
        # terrain, moved onto the facade's own sparse points where at least wall_snap_points of them lie
        # within wall_snap_m of it (else half a cell out from the roof's grid); the facades the aerial
        # images see at grazing angles hold too few points for a plane of their own
        "roof_walls": False,
        "roof_min_height_m": 2.5,
        "roof_min_area_m2": 40.0,
        "roof_outline_m": 1.0,
        "roof_clutter_m": 3.0,  # what stands on a roof (ducts, stair houses) is lower than this
        "wall_snap_m": 1.5,
        "wall_snap_points": 5,
        "wall_max_tilt_deg": 8.0,
        "wall_min_width_m": 4.0,
        "wall_max_drop_m": 30.0,
        "terrain_radius_m": 10.0,
        "terrain_quantile": 0.1,
        "terrain_min_points": 10,
        # the planes found among the sparse points and points of the aerial images' dense stereo surface
        # (services.views.stereo, one per dense_voxel_m voxel): facades the sparse model hardly holds get
        # a plane of their own ("none": the sparse points alone), or the points of learned tracks across
        # the aerial images triangulated on the model's poses ("tracks", services.views.tracks). The
        # renderer builds them.
        "dense_points": "none",
        "dense_voxel_m": 0.5,
        "dense_max_tilt_deg": -1.0,  # >= 0: only the dense points of walls (normal this near horizontal)
    },
}


@dataclass
class Plane:
    """n . x + d = 0 (unit normal n), its in-plane basis (e1, e2) from origin o, and its occupied cells
    (occ[row, col] of cells `cell` metres wide from the corner lo of the grid, in (e1, e2) coordinates)."""

    n: np.ndarray
    d: float
    o: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    lo: np.ndarray
    cell: float
    occ: np.ndarray
    corners: np.ndarray  # (4, 3) world corners of the grid (for culling)
    num_points: int


def _hypotheses(
    P: np.ndarray, alive: np.ndarray, tree: cKDTree, conf: dict, rng
) -> tuple[np.ndarray, np.ndarray]:
    """(M, 4) planes (n, d) through a random live point and two live points within sample_radius_m, and
    (M,) those random points' indices."""
    live = np.nonzero(alive)[0]
    seeds = rng.choice(live, min(int(conf["hypotheses"]), len(live)), replace=False)
    out, used = [], []
    for i, nb in zip(seeds, tree.query_ball_point(P[seeds], float(conf["sample_radius_m"])), strict=True):
        nb = [j for j in nb if alive[j] and j != i]
        if len(nb) < 2:
            continue
        j, k = rng.choice(nb, 2, replace=False)
        n = np.cross(P[j] - P[i], P[k] - P[i])
        norm = np.linalg.norm(n)
        if norm > 1e-3:
            n = n / norm
            out.append([*n, -n @ P[i]])
            used.append(i)
    return np.asarray(out, float).reshape(-1, 4), np.asarray(used, int)


def _connected(P: np.ndarray, idx: np.ndarray, core: np.ndarray, gap: float) -> np.ndarray:
    """The points of idx (indices into P) connected to those of `core` (a subset) by hops under `gap`."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(P[idx]).query_pairs(gap, output_type="ndarray")
    n = len(idx)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    keep = np.unique(label[np.isin(idx, core)])
    return idx[np.isin(label, keep)]


def _local_plane(
    P: np.ndarray, alive: np.ndarray, tree: cKDTree, hyp: np.ndarray, seeds: np.ndarray, c: dict
) -> tuple[int, np.ndarray, np.ndarray]:
    """The hypothesis with the most live inliers within support_radius_m of its sample, refit: (its
    support, plane (4,), the live inliers connected to that support)."""
    tol = float(c["inlier_m"])
    balls = tree.query_ball_point(P[seeds], float(c["support_radius_m"]))
    support = []
    for h, ball in zip(hyp, balls, strict=True):
        b = np.asarray(ball, int)
        b = b[alive[b]]
        support.append(b[np.abs(P[b] @ h[:3] + h[3]) < tol])
    best = int(np.argmax([len(x) for x in support]))
    core = support[best]
    if len(core) < 3:
        return len(core), hyp[best], core
    plane, _ = _refine(P, core, hyp[best], tol)
    live = np.nonzero(alive)[0]
    inl = live[np.abs(P[live] @ plane[:3] + plane[3]) < tol]
    inl = _connected(P, inl, core, float(c["connected_m"]))
    if len(inl) >= 3:  # the refit on the connected inliers
        plane, _ = _refine(P, inl, plane, tol)
    return len(core), plane, inl


def _refine(P: np.ndarray, live: np.ndarray, plane: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares refit of a plane (4,) to its inliers among the points `live`, twice: (plane, inliers)."""
    Q = P[live]
    inl = live[np.abs(Q @ plane[:3] + plane[3]) < tol]
    for _ in range(2):
        if len(inl) < 3:
            break
        c = P[inl].mean(0)
        n = np.linalg.svd(P[inl] - c, full_matrices=False)[2][2]  # not the (N, N) U
        plane = np.array([*n, -n @ c])
        inl = live[np.abs(Q @ n + plane[3]) < tol]
    return plane, inl


def detect_planes(
    P: np.ndarray, conf: dict | None = None, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Planes of the points P (N, 3) by sequential RANSAC with local samples: [(plane (4,), inlier
    indices)], best supported first; each point belongs to at most one plane."""
    c = {**confs["default"], **(conf or {})}
    rng = np.random.default_rng(seed)
    tree = cKDTree(P)
    alive = np.ones(len(P), bool)
    tol, min_in = float(c["inlier_m"]), int(c["min_inliers"])
    planes: list[tuple[np.ndarray, np.ndarray]] = []
    misses = 0
    while alive.sum() >= min_in and len(planes) < int(c["max_planes"]) and misses < int(c["max_misses"]):
        hyp, seeds = _hypotheses(P, alive, tree, c, rng)
        live = np.nonzero(alive)[0]
        if len(hyp) == 0:
            misses += 1
            continue
        if float(c["connected_m"]) > 0:
            count, plane, inl = _local_plane(P, alive, tree, hyp, seeds, c)
        else:
            counts = (np.abs(P[live] @ hyp[:, :3].T + hyp[:, 3]) < tol).sum(0)
            best = int(np.argmax(counts))
            count = int(counts[best])
            plane, inl = _refine(P, live, hyp[best], tol)
        if count < min_in or len(inl) < min_in:
            misses += 1
            continue
        planes.append((plane, inl))
        alive[inl] = False
        misses = 0
    return planes


def _occupancy(uv: np.ndarray, cell: float, close: int) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells of in-plane points uv (N, 2): (grid corner lo (2,), bool occ (rows, cols)),
    holes up to `close` cells closed and each connected part filled to its convex hull."""
    pad = close + 1  # the closing must not reach the grid's border (there it would not erode back)
    lo = uv.min(0) - pad * cell
    ij = np.floor((uv - lo) / cell).astype(int)
    cols, rows = ij.max(0) + pad + 1
    occ = np.zeros((rows, cols), np.uint8)
    occ[ij[:, 1], ij[:, 0]] = 1
    occ = cv2.morphologyEx(occ, cv2.MORPH_CLOSE, np.ones((close, close), np.uint8))
    n, comp = cv2.connectedComponents(occ, connectivity=8)
    filled = np.zeros_like(occ)
    for k in range(1, n):
        ys, xs = np.nonzero(comp == k)
        hull = cv2.convexHull(np.stack([xs, ys], 1).astype(np.int32))
        cv2.fillConvexPoly(filled, hull, 1)
    return lo, filled.astype(bool)


def is_wall(n: np.ndarray, conf: dict) -> bool:
    """Whether a plane of unit normal n (3,) is a wall: its normal within wall_max_tilt_deg of horizontal."""
    return abs(float(n[2])) < np.sin(np.radians(float(conf["wall_max_tilt_deg"])))


def _basis(n: np.ndarray, upright: bool) -> tuple[np.ndarray, np.ndarray]:
    """An in-plane basis (e1, e2) for unit normal n; `upright`: e1 horizontal and e2 up the plane."""
    if upright:
        e2 = np.array([0.0, 0.0, 1.0]) - n[2] * n
        e2 /= np.linalg.norm(e2)
        return np.cross(e2, n), e2
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def make_plane(P: np.ndarray, plane: np.ndarray, conf: dict, terrain: Terrain | None = None) -> Plane:
    """A Plane of its parameters (4,) and its points P (N, 3); with `terrain` (conf walls_to_terrain), a
    wall's columns continued down to it (`extend_to_terrain`)."""
    n, d = plane[:3] / np.linalg.norm(plane[:3]), float(plane[3])
    wall = terrain is not None and is_wall(n, conf)
    e1, e2 = _basis(n, upright=wall)
    m = P.mean(0)
    o = m - (n @ m + d) * n
    uv = np.stack([(P - o) @ e1, (P - o) @ e2], 1)
    cell = float(conf["cell_m"])
    lo, occ = _occupancy(uv, cell, int(conf["close_cells"]))
    if wall and terrain is not None and occ.shape[1] * cell >= float(conf["wall_min_width_m"]):
        lo, occ = extend_to_terrain(o, e1, e2, lo, cell, occ, terrain, float(conf["wall_max_drop_m"]))
    ext = np.array([[0, 0], [occ.shape[1], 0], [0, occ.shape[0]], [occ.shape[1], occ.shape[0]]]) * cell + lo
    corners = o + ext[:, :1] * e1 + ext[:, 1:] * e2
    return Plane(n, d, o, e1, e2, lo, cell, occ, corners, len(P))


class Terrain:
    """The terrain's height under horizontal positions: a low quantile of the heights of the points near
    each (the street, not the roofs and facades beside it)."""

    def __init__(self, P: np.ndarray, conf: dict):
        self.P = P
        self.tree = cKDTree(P[:, :2])
        self.radius = float(conf["terrain_radius_m"])
        self.quantile = float(conf["terrain_quantile"])
        self.min_points = int(conf["terrain_min_points"])
        self.floor = float(np.quantile(P[:, 2], 0.01)) if len(P) else 0.0  # below: outliers

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Heights (M,) at xy (M, 2); NaN where fewer than terrain_min_points points are near."""
        out = np.full(len(xy), np.nan)
        for i, near in enumerate(self.tree.query_ball_point(xy, self.radius)):
            if len(near) >= self.min_points:
                out[i] = max(float(np.quantile(self.P[near, 2], self.quantile)), self.floor)
        return out


def extend_to_terrain(
    o: np.ndarray,
    e1: np.ndarray,
    e2: np.ndarray,
    lo: np.ndarray,
    cell: float,
    occ: np.ndarray,
    terrain: Terrain,
    max_drop: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A wall's occupancy grid (rows up e2, columns along the horizontal e1) with each occupied column
    filled from its lowest occupied cell down to the terrain under it, when that is at most `max_drop`
    below: (lo (2,), occ (rows', cols)), the grid grown downwards as needed."""
    cols = np.nonzero(occ.any(0))[0]
    if len(cols) == 0:
        return lo, occ
    bottom = occ[:, cols].argmax(0)  # the lowest occupied row of each column
    foot = o + (lo[0] + (cols[:, None] + 0.5) * cell) * e1 + (lo[1] + bottom[:, None] * cell) * e2
    drop = foot[:, 2] - terrain.height(foot[:, :2])  # NaN where the terrain is unknown
    ok = (drop > cell) & (drop <= max_drop)
    if not ok.any():
        return lo, occ
    rows_down = np.zeros(len(cols), int)
    rows_down[ok] = np.ceil(drop[ok] / (e2[2] * cell)).astype(int)
    start = bottom - rows_down
    pad = max(0, -int(start.min()))
    occ = np.concatenate([np.zeros((pad, occ.shape[1]), bool), occ], 0)
    for c, a, b in zip(cols[ok], start[ok] + pad, bottom[ok] + pad, strict=True):
        occ[a:b, c] = True
    return np.array([lo[0], lo[1] - pad * cell]), occ


def wall_plane(a: np.ndarray, b: np.ndarray, z0: float, z1: float, cell: float) -> Plane:
    """A vertical wall over the horizontal segment a -> b (world points; their heights ignored) from
    height z0 up to z1, fully occupied."""
    up = np.array([0.0, 0.0, 1.0])
    a = np.array([a[0], a[1], z0], float)
    e1 = np.array([b[0] - a[0], b[1] - a[1], 0.0])
    length = float(np.linalg.norm(e1))
    e1 /= length
    n = np.cross(e1, up)
    rows, cols = int(np.ceil((z1 - z0) / cell - 1e-6)), int(round(length / cell))
    occ = np.ones((max(1, rows), max(1, cols)), bool)
    ext = np.array([[0, 0], [occ.shape[1], 0], [0, occ.shape[0]], [occ.shape[1], occ.shape[0]]]) * cell
    corners = a + ext[:, :1] * e1 + ext[:, 1:] * up
    return Plane(n, float(-n @ a), a, e1, up, np.zeros(2), cell, occ, corners, 0)


def roof_walls(planes: list[Plane], P: np.ndarray, terrain: Terrain, conf: dict) -> list[Plane]:
    """Walls under the outlines of the roofs among `planes` (conf roof_walls), from the roof down to the
    terrain; each moved onto the sparse points P (N, 3) of its facade where they are enough."""
    tree = cKDTree(P[:, :2])
    walls = []
    min_cos = np.cos(np.radians(float(conf["wall_max_tilt_deg"])))
    for pl in planes:
        if abs(float(pl.n[2])) < min_cos:
            continue
        cell = pl.cell
        contours, _ = cv2.findContours(pl.occ.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for cnt in contours:
            if cv2.contourArea(cnt) * cell**2 < float(conf["roof_min_area_m2"]) or not _open_above(
                pl, cnt, P, tree, float(conf["roof_clutter_m"])
            ):
                continue  # a balcony, a canopy, a car: not a building's roof
            poly = cv2.approxPolyDP(cnt, float(conf["roof_outline_m"]) / cell, True)[:, 0, :].astype(float)
            world = (
                pl.o
                + (pl.lo[0] + (poly[:, :1] + 0.5) * cell) * pl.e1
                + (pl.lo[1] + (poly[:, 1:] + 0.5) * cell) * pl.e2
            )
            for a, b in zip(world, np.roll(world, -1, 0), strict=True):
                wall = _roof_wall(a, b, world.mean(0), P, tree, terrain, conf)
                if wall is not None:
                    walls.append(wall)
    return walls


def _open_above(roof: Plane, contour: np.ndarray, P: np.ndarray, tree: cKDTree, clutter_m: float) -> bool:
    """Whether nothing stands on the horizontal plane `roof` within its outline `contour` (cells): at
    most 30% of the sparse points P (N, 3) over it lie more than clutter_m above it (a balcony or a
    canopy has its facade's points above it; a roof has the sky, and what stands on it is low)."""
    inside = np.zeros_like(roof.occ, np.uint8)
    cv2.drawContours(inside, [contour], -1, 1, -1)
    ii, jj = np.nonzero(inside)
    cells = roof.o + (roof.lo[0] + (jj[:, None] + 0.5) * roof.cell) * roof.e1
    cells = cells + (roof.lo[1] + (ii[:, None] + 0.5) * roof.cell) * roof.e2
    near = np.unique(
        np.concatenate([np.asarray(x, int) for x in tree.query_ball_point(cells[:, :2], roof.cell * 0.71)])
    )
    if len(near) == 0:
        return True
    height = P[near, 2] - float(cells[:, 2].mean())
    return float(np.mean(height > clutter_m)) <= 0.3


def _roof_wall(
    a: np.ndarray,
    b: np.ndarray,
    centre: np.ndarray,
    P: np.ndarray,
    tree: cKDTree,
    terrain: Terrain,
    conf: dict,
) -> Plane | None:
    """The wall under the edge a -> b of a roof outline around `centre` (through its boundary cells'
    centres), or None when too short, too low or over unknown terrain: the edge moved out half a cell,
    fitted to the roof's outermost points along it, then onto the facade's own points where they are
    enough (the sparse points P (N, 3), `tree` of their horizontal positions)."""
    length = float(np.hypot(*(b - a)[:2]))
    if length < float(conf["wall_min_width_m"]):
        return None
    mid = (a + b) / 2
    ground, top = float(terrain.height(mid[None, :2])[0]), float(mid[2])
    if not np.isfinite(ground) or top - ground < float(conf["roof_min_height_m"]):
        return None
    cell = float(conf["cell_m"])
    e1 = np.array([*(b - a)[:2] / length, 0.0])
    n = np.array([e1[1], -e1[0], 0.0])
    out = n if (mid - centre) @ n > 0 else -n  # the outline is convex: its cells are filled to their hull
    a, b = a + 0.5 * cell * out, b + 0.5 * cell * out
    Q = P[np.asarray(tree.query_ball_point(mid[:2], length / 2 + 2.0), int)]
    if len(Q):
        a, b = _fit_rim(a, b, out, Q, top, conf)
        a, b = _snap_to_facade(a, b, out, Q, ground, top, conf)
    return wall_plane(a, b, ground, top, cell)


def _fit_rim(
    a: np.ndarray, b: np.ndarray, out: np.ndarray, Q: np.ndarray, top: float, conf: dict
) -> tuple[np.ndarray, np.ndarray]:
    """The roof edge a -> b (outward normal `out`) as the line through the roof's outermost points Q
    (N, 3) along it: its angle from a line fitted to the 98th percentile of their offsets across it per
    metre along it, its offset the 99th percentile of all their offsets from that line; unchanged with
    fewer than three metres of them."""
    cell = float(conf["cell_m"])
    length = float(np.hypot(*(b - a)[:2]))
    e1 = (b - a) / np.linalg.norm(b - a)
    along, dist = (Q - a) @ e1, (Q - a) @ out
    rim = (along > 0) & (along < length) & (np.abs(Q[:, 2] - top) < 0.3) & (np.abs(dist) < 2.0 * cell)
    bins = np.floor(along[rim]).astype(int)
    xs, ys = [], []
    for k in np.unique(bins):
        d = dist[rim][bins == k]
        if len(d) >= 2:
            xs.append(k + 0.5)
            ys.append(float(np.quantile(d, 0.98)))
    if len(xs) < 3:
        return a, b
    slope = float(np.polyfit(xs, ys, 1)[0])  # each metre's percentile is biased inwards alike: the angle
    offset = float(np.quantile(dist[rim] - slope * along[rim], 0.99))  # the edge: from all of them at once
    return a + offset * out, b + (offset + slope * length) * out


def _snap_to_facade(
    a: np.ndarray, b: np.ndarray, out: np.ndarray, Q: np.ndarray, ground: float, top: float, conf: dict
) -> tuple[np.ndarray, np.ndarray]:
    """The wall a -> b moved across itself onto the median of the facade's points among Q (N, 3): those
    within wall_snap_m of it, between the street and the roof; unchanged with fewer than
    wall_snap_points of them."""
    length = float(np.linalg.norm((b - a)[:2]))
    e1 = np.array([*(b - a)[:2] / length, 0.0])
    n = np.array([e1[1], -e1[0], 0.0])
    n = n if n @ out > 0 else -n
    along, dist = (Q - a) @ e1, (Q - a) @ n
    on = (along > 0) & (along < length) & (np.abs(dist) < float(conf["wall_snap_m"]))
    on &= (Q[:, 2] > ground + 0.5) & (Q[:, 2] < top - 0.5)  # not the roof's or the street's points
    if on.sum() < int(conf["wall_snap_points"]):
        return a, b
    shift = float(np.median(dist[on]))
    return a + shift * n, b + shift * n


class PlaneProxy:
    """The planes of an aerial model, ray cast at any pinhole camera of its frame."""

    def __init__(self, planes: list[Plane], conf: dict | None = None):
        self.planes = planes
        self.conf = {**confs["default"], **(conf or {})}

    @classmethod
    def from_points(cls, P: np.ndarray, conf: dict | None = None) -> PlaneProxy:
        c = {**confs["default"], **(conf or {})}
        found = detect_planes(P, c)
        terrain = Terrain(P, c) if c["walls_to_terrain"] or c["roof_walls"] else None
        planes = [
            make_plane(P[inl], plane, c, terrain if c["walls_to_terrain"] else None) for plane, inl in found
        ]
        if c["roof_walls"] and terrain is not None:
            walls = roof_walls(planes, P, terrain, c)
            logger.info("plane proxy: %d walls under the roofs' outlines", len(walls))
            planes += walls
        return cls(planes, c)

    @classmethod
    def from_model(
        cls,
        model: str | Path | pycolmap.Reconstruction,
        conf: dict | None = None,
        dense: np.ndarray | None = None,
    ) -> PlaneProxy:
        """The planes of a COLMAP model's (a folder or a loaded Reconstruction) points seen by at least
        min_track_length images, and of the `dense` points (N, 3) given beside them."""
        c = {**confs["default"], **(conf or {})}
        rec = model if isinstance(model, pycolmap.Reconstruction) else pycolmap.Reconstruction(str(model))
        P = np.array(
            [p.xyz for p in rec.points3D.values() if p.track.length() >= int(c["min_track_length"])], float
        ).reshape(-1, 3)
        n_sparse = len(P)
        if dense is not None and len(dense):
            P = np.concatenate([P, np.asarray(dense, float).reshape(-1, 3)])
        proxy = cls.from_points(P, c) if len(P) >= int(c["min_inliers"]) else cls([], c)
        covered = sum(p.num_points for p in proxy.planes)
        logger.info(
            "plane proxy: %d planes hold %d of %d sparse and %d dense points",
            len(proxy.planes), covered, n_sparse, len(P) - n_sparse,
        )  # fmt: skip
        return proxy

    @staticmethod
    def _cast(pl: Plane, C: np.ndarray, rays_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays from the camera centre C (3,) along rays_w (N, 3) (world direction per unit z-depth)
        against one plane: (indices of the rays that meet it in an occupied cell, their z-depths)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(pl.n @ C + pl.d) / (rays_w @ pl.n)
        idx = np.nonzero(t > 0.1)[0]
        Y = C + rays_w[idx] * t[idx, None] - pl.o
        ij = np.floor((np.stack([Y @ pl.e1, Y @ pl.e2], 1) - pl.lo) / pl.cell).astype(int)
        ok = (ij >= 0).all(1) & (ij[:, 0] < pl.occ.shape[1]) & (ij[:, 1] < pl.occ.shape[0])
        hit = np.zeros(len(idx), bool)
        hit[ok] = pl.occ[ij[ok, 1], ij[ok, 0]]
        return idx[hit], t[idx[hit]]

    def depth(self, camera: Camera, pose: Pose, coarse: int = 8) -> np.ndarray:
        """z-depth (H, W) float32 of the nearest occupied plane along each pixel's ray, 0 where none.
        Each plane is cast first at every `coarse`-th pixel, then at the pixels around its coarse hits."""
        H, W = camera.height, camera.width
        hc, wc = -(-H // coarse), -(-W // coarse)
        vc, uc = np.mgrid[0:hc, 0:wc]
        centres = np.stack([(uc.ravel() + 0.5) * coarse, (vc.ravel() + 0.5) * coarse], 1).astype(float)
        C = pose.center

        def rays(uv: np.ndarray) -> np.ndarray:  # world direction per unit z-depth
            return pose.unproject(camera.K, uv, np.ones(len(uv))) - C

        coarse_rays = rays(centres)
        v, u = np.mgrid[0:H, 0:W]
        pixel_rays = rays(np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1).astype(float))
        best = np.full(H * W, np.inf)
        kernel = np.ones((3, 3), np.uint8)
        for pl in self.planes:
            idx, _ = self._cast(pl, C, coarse_rays)
            if len(idx) == 0:
                continue
            mask = np.zeros(hc * wc, np.uint8)
            mask[idx] = 1
            mask = cv2.dilate(mask.reshape(hc, wc), kernel)
            fine = cv2.resize(mask, (wc * coarse, hc * coarse), interpolation=cv2.INTER_NEAREST)[:H, :W]
            pix = np.flatnonzero(fine)
            hit, t = self._cast(pl, C, pixel_rays[pix])
            near = t < best[pix[hit]]
            best[pix[hit][near]] = t[near]
        best[~np.isfinite(best)] = 0.0
        return best.reshape(H, W).astype(np.float32)

    def fuse(
        self, camera: Camera, pose: Pose, depth: np.ndarray, free_space: FreeSpace | None = None
    ) -> np.ndarray:
        """The planes' depth combined with another depth (H, W) of the same view (the 3DGS's), see
        `combine`; with `free_space` (world points (N, 3) -> whether the aerial images see through
        them), the other depth's surfaces in front of the planes, or where no plane is hit, only where
        they do not (elsewhere the plane behind, or no depth: 0)."""
        planes = self.depth(camera, pose)
        if free_space is not None:
            front = (depth > 0) & (planes > 0) & (depth < planes * (1.0 - self.conf["occluder"]))
            tested = front | ((depth > 0) & (planes == 0))
            if tested.any():  # a floater is no surface: the plane behind it, or none
                depth = np.where(self._floaters(camera, pose, depth, tested, free_space), 0.0, depth)
        return combine(planes, depth, self.conf["occluder"])

    def _floaters(
        self, camera: Camera, pose: Pose, depth: np.ndarray, tested: np.ndarray, free_space: FreeSpace
    ) -> np.ndarray:
        """free_space of the surface at depth (H, W), at the centre of each k x k cell (k:
        free_space_stride) whose centre is `tested` (H, W), the verdict spread over the cell."""
        k = max(1, int(self.conf["free_space_stride"]))
        H, W = depth.shape
        ys = np.minimum(np.arange(0, H, k) + k // 2, H - 1)
        xs = np.minimum(np.arange(0, W, k) + k // 2, W - 1)
        cell_v, cell_u = np.nonzero(tested[np.ix_(ys, xs)])
        v, u = ys[cell_v], xs[cell_u]
        X = pose.unproject(camera.K, np.stack([u + 0.5, v + 0.5], 1), depth[v, u].astype(np.float64))
        cells = np.zeros((len(ys), len(xs)), bool)
        cells[cell_v, cell_u] = free_space(X)
        return np.repeat(np.repeat(cells, k, 0), k, 1)[:H, :W] & tested


def combine(plane_depth: np.ndarray, depth: np.ndarray, occluder: float = 0.15) -> np.ndarray:
    """The planes' depth where a plane is hit, unless the other depth (the 3DGS's) sees something more
    than `occluder` (relative) in front of it; the other depth elsewhere."""
    out = np.where(plane_depth > 0, plane_depth, depth)
    front = (depth > 0) & (plane_depth > 0) & (depth < plane_depth * (1.0 - occluder))
    return np.where(front, depth, out).astype(np.float32)
