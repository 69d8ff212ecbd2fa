"""Procedural urban blocks: buildings (boxes with setbacks and rooftop structures), streets, sidewalks,
yards, and clutter (cars, kiosks, trees, lamps, kerbs), in the local ENU frame (metres, z up, ground z=0).

The layout is a regular grid of blocks separated by roads. The central `blocks` are surveyed; `context`
rings of further blocks around them only give the cameras something realistic to look at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .materials import (
    BOX_MATERIALS,
    MAT_BUILDING,
    MAT_BUSH,
    MAT_CAR,
    MAT_CROWN,
    MAT_KERB,
    MAT_KIOSK,
    MAT_POLE,
    MAT_ROOFBOX,
    MAT_TRUNK,
    NPAR,
    P_AXIS,
    P_B2,
    P_BAY,
    P_DOOR,
    P_FB,
    P_FG,
    P_FLOOR,
    P_FR,
    P_G2,
    P_GFLOOR,
    P_PARAPET,
    P_PHOTO,
    P_R2,
    P_RELIEF,
    P_ROOF,
    P_SEED,
    P_SHOP,
    P_STYLE,
    P_WALL,
    P_WALL_M,
    P_WINH,
    P_WINW,
    P_Z0,
    SPHERE_MATERIALS,
    Z_GRASS,
    Z_PARKING,
    Z_PAVED,
    Z_ROAD,
    Z_SIDEWALK,
    Z_UNDER,
    ZONES,
)

ZONE_RES = 0.25  # metres per zone raster cell; every layout coordinate is a multiple of it

PLASTER = [
    (0.60, 0.52, 0.36),
    (0.55, 0.36, 0.12),
    (0.68, 0.66, 0.62),
    (0.60, 0.38, 0.33),
    (0.38, 0.38, 0.37),
    (0.35, 0.42, 0.48),
    (0.66, 0.52, 0.18),
    (0.35, 0.45, 0.30),
]
BRICK = [(0.33, 0.11, 0.06), (0.26, 0.14, 0.08), (0.52, 0.40, 0.22), (0.20, 0.10, 0.07)]
PANEL = [(0.42, 0.41, 0.39), (0.55, 0.54, 0.50)]
ROOF = [(0.32, 0.31, 0.29), (0.07, 0.07, 0.075), (0.12, 0.20, 0.06), (0.30, 0.10, 0.07)]
FRAMES = [(0.7, 0.7, 0.68), (0.08, 0.08, 0.09), (0.16, 0.09, 0.05), (0.35, 0.36, 0.36)]
CARS = [
    (0.75, 0.75, 0.75),
    (0.03, 0.03, 0.035),
    (0.45, 0.46, 0.48),
    (0.25, 0.25, 0.26),
    (0.50, 0.04, 0.03),
    (0.05, 0.12, 0.40),
    (0.05, 0.18, 0.10),
    (0.60, 0.45, 0.10),
    (0.80, 0.78, 0.70),
]


def _snap(v: float, step: float = ZONE_RES) -> float:
    return round(v / step) * step


@dataclass
class Scene:
    """Primitives and ground layout. Boxes (N, 6): lo xyz, hi xyz; spheres (M, 4): centre xyz, radius.

    `*mat` are material ids, `*par` (., NPAR) parameter rows (materials.py), `*group` the clutter group of
    each primitive (-1: buildings, kerbs), so that clutter in the way of a ground camera can be dropped.
    zone (Hz, Wz) uint8 ground zones with zmeta = (x0, y0, res); lay = (X0, Y0, Px, Py, road, nx, ny,
    sidewalk) describes the block grid; surveyed = (xmin, ymin, xmax, ymax) of the surveyed blocks with
    the roads around them.
    """

    boxes: np.ndarray
    bmat: np.ndarray
    bpar: np.ndarray
    bgroup: np.ndarray
    sph: np.ndarray
    smat: np.ndarray
    spar: np.ndarray
    sgroup: np.ndarray
    zone: np.ndarray
    zmeta: np.ndarray
    lay: np.ndarray
    surveyed: np.ndarray
    blocks: list[dict] = field(default_factory=list)
    # clutter groups there in one capture only ("aerial" or "ground"): cars parked or gone between them
    transient: dict[int, str] = field(default_factory=dict)

    def for_capture(self, capture: str) -> Scene:
        """The scene as the capture `capture` saw it: without the transient groups of the other one
        (this scene itself when it has none)."""
        gone = {g for g, c in self.transient.items() if c != capture}
        return self.without_groups(gone) if gone else self

    def without_groups(self, groups: set[int]) -> Scene:
        """This scene without the primitives of the clutter groups `groups`."""
        kb, ks = ~np.isin(self.bgroup, list(groups)), ~np.isin(self.sgroup, list(groups))
        return Scene(
            self.boxes[kb], self.bmat[kb], self.bpar[kb], self.bgroup[kb],
            self.sph[ks], self.smat[ks], self.spar[ks], self.sgroup[ks],
            self.zone, self.zmeta, self.lay, self.surveyed, self.blocks,
            {g: c for g, c in self.transient.items() if g not in groups},
        )  # fmt: skip

    def drop_clutter_near(self, points: np.ndarray, clearance: float) -> Scene:
        """Remove clutter groups with a primitive within `clearance` (bounding box) of any point (K, 3)."""
        points = np.asarray(points, float).reshape(-1, 3)
        bad: set[int] = set()
        lo = np.concatenate([self.boxes[:, :3], self.sph[:, :3] - self.sph[:, 3:]]) - clearance
        hi = np.concatenate([self.boxes[:, 3:], self.sph[:, :3] + self.sph[:, 3:]]) + clearance
        groups = np.concatenate([self.bgroup, self.sgroup])
        for p in points:
            near = np.all((lo <= p) & (p <= hi), axis=1) & (groups >= 0)
            bad.update(int(g) for g in groups[near])
        return self.without_groups(bad)

    def grid(self, cell: float = 4.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Uniform xy grid over all primitives: gmeta (6 + nx*ny,) = (x0, y0, cell, nx, ny, zmax, then
        the top z of each cell's content), cstart (nx*ny+1,), citems (K,): box i as i, sphere j as N + j."""
        lo = np.concatenate([self.boxes[:, :3], self.sph[:, :3] - self.sph[:, 3:], np.zeros((1, 3))])
        hi = np.concatenate([self.boxes[:, 3:], self.sph[:, :3] + self.sph[:, 3:], np.ones((1, 3))])
        x0, y0 = math.floor(lo[:, 0].min()) - 1.0, math.floor(lo[:, 1].min()) - 1.0
        nx = int(math.ceil((hi[:, 0].max() + 1.0 - x0) / cell))
        ny = int(math.ceil((hi[:, 1].max() + 1.0 - y0) / cell))
        zmax = float(hi[:, 2].max()) + 0.01
        cells: list[list[int]] = [[] for _ in range(nx * ny)]
        ctop = np.full(nx * ny, -1.0)
        nb = len(self.boxes)
        for k in range(len(lo) - 1):
            i0 = max(int((lo[k, 0] - x0) // cell), 0)
            i1 = min(int((hi[k, 0] - x0) // cell), nx - 1)
            j0 = max(int((lo[k, 1] - y0) // cell), 0)
            j1 = min(int((hi[k, 1] - y0) // cell), ny - 1)
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    cells[j * nx + i].append(k)
                    ctop[j * nx + i] = max(ctop[j * nx + i], hi[k, 2])
        cstart = np.zeros(nx * ny + 1, np.int64)
        cstart[1:] = np.cumsum([len(c) for c in cells])
        citems = np.array([k for c in cells for k in c], np.int64)
        assert nb + len(self.sph) == len(lo) - 1
        gmeta = np.concatenate([[x0, y0, cell, nx, ny, zmax], ctop]).astype(np.float64)
        return gmeta, cstart, citems

    def to_json(self) -> dict:
        """Primitives and layout as plain JSON (for gt/scene.json)."""
        r = lambda a: np.round(a, 4).tolist()  # noqa: E731
        return {
            "boxes": {
                "columns": ["xmin", "ymin", "zmin", "xmax", "ymax", "zmax"],
                "lohi": r(self.boxes),
                "material": [BOX_MATERIALS[int(m)] for m in self.bmat],
                "params": r(self.bpar),
            },
            "spheres": {
                "columns": ["x", "y", "z", "radius"],
                "xyzr": r(self.sph),
                "material": [SPHERE_MATERIALS[int(m)] for m in self.smat],
                "params": r(self.spar),
            },
            "ground": {
                "zones": ZONES,
                "zone_origin_res": r(self.zmeta),
                "zone_shape": list(self.zone.shape),
                "layout": dict(
                    zip(
                        ["x0", "y0", "pitch_x", "pitch_y", "road", "nx", "ny", "sidewalk"],
                        r(self.lay),
                        strict=True,
                    )
                ),
                "blocks": self.blocks,
            },
            "surveyed": r(self.surveyed),
        }


class _Builder:
    """Collects primitives while the layout is generated."""

    def __init__(self, rng: np.random.Generator, photo: bool, walls: np.ndarray | None = None):
        self.rng = rng
        self.photo = photo
        self.walls = walls  # metres per pixel of each wall photo (services.synth.walls), None: none
        self.cars: list[int] = []  # the groups of the parked cars
        self.boxes: list[list[float]] = []
        self.bmat: list[int] = []
        self.bpar: list[np.ndarray] = []
        self.bgroup: list[int] = []
        self.sph: list[list[float]] = []
        self.smat: list[int] = []
        self.spar: list[np.ndarray] = []
        self.sgroup: list[int] = []
        self.n_seed = 1
        self.n_group = 0

    def seed(self) -> int:
        self.n_seed += 1
        return self.n_seed

    def group(self) -> int:
        self.n_group += 1
        return self.n_group

    def par(self, colour=(0.5, 0.5, 0.5), *values: dict[int, float]) -> np.ndarray:
        """A parameter row with colour, a fresh texture seed and the given {index: value} entries."""
        p = np.zeros(NPAR)
        p[0:3] = colour
        p[P_SEED] = self.seed()
        p[P_PHOTO] = -1.0
        p[P_WALL] = -1.0
        for kw in values:
            for k, v in kw.items():
                p[k] = v
        return p

    def box(self, lo, hi, mat: int, par: np.ndarray, group: int = -1) -> None:
        self.boxes.append([*lo, *hi])
        self.bmat.append(mat)
        self.bpar.append(par)
        self.bgroup.append(group)

    def sphere(self, c, r: float, mat: int, par: np.ndarray, group: int) -> None:
        self.sph.append([*c, r])
        self.smat.append(mat)
        self.spar.append(par)
        self.sgroup.append(group)

    def colour(self, palette, spread: float = 0.12) -> np.ndarray:
        c = np.array(palette[self.rng.integers(len(palette))], float)
        return np.clip(c * self.rng.uniform(1 - spread, 1 + spread, 3), 0.01, 0.9)

    # ---------------------------------------------------------------------------- objects
    def building(self, fp: tuple[float, float, float, float], conf: dict) -> None:
        """A building on footprint (x0, y0, x1, y1): main box, maybe a setback box, rooftop structures."""
        rng = self.rng
        x0, y0, x1, y1 = fp
        hf = rng.uniform(2.9, 3.5)
        hg = rng.uniform(3.6, 4.6)
        parapet = rng.uniform(0.5, 1.1)
        hmin, hmax = conf["height"]
        n_lo = max(1, math.ceil((hmin - hg - parapet) / hf))
        n_hi = max(n_lo, math.floor((hmax - hg - parapet) / hf))
        n = int(rng.integers(n_lo, n_hi + 1))
        H = hg + n * hf + parapet
        style = int(rng.choice(3, p=[0.55, 0.3, 0.15]))
        colour = self.colour([PLASTER, BRICK, PANEL][style])
        roof = int(rng.choice(4, p=[0.4, 0.3, 0.15, 0.15]))
        common = {
            P_STYLE: style,
            P_FLOOR: hf,
            P_BAY: rng.uniform(2.4, 3.6),
            P_WINW: rng.uniform(0.4, 0.62),
            P_WINH: rng.uniform(0.45, 0.62),
            P_SHOP: 0.0 if rng.random() < 0.4 else rng.uniform(0.4, 1.0),
            P_ROOF: roof,
            P_PARAPET: parapet,
            P_DOOR: rng.random(),
        }
        rc = self.colour([ROOF[roof]], 0.15)
        frame = self.colour(FRAMES, 0.05)
        photo = rng.uniform(10.0, 20.0)  # drawn either way: the layout does not depend on self.photo
        photo = photo if self.photo else -1.0
        for k, v in zip((P_R2, P_G2, P_B2, P_FR, P_FG, P_FB), (*rc, *frame), strict=True):
            common[k] = v
        par = self.par(colour, common, {P_GFLOOR: hg, P_Z0: 0.0, P_PHOTO: photo})
        self.box((x0, y0, 0.0), (x1, y1, H), MAT_BUILDING, par)
        if conf.get("relief"):
            self.facade_details(par, (x0, y0, x1, y1), n, conf)
        top = (x0, y0, x1, y1, H)
        if n >= 3 and rng.random() < 0.35:
            s = [_snap(rng.uniform(1.5, 4.0)) for _ in range(4)]
            bx0, by0, bx1, by1 = x0 + s[0], y0 + s[1], x1 - s[2], y1 - s[3]
            if bx1 - bx0 >= 5.0 and by1 - by0 >= 5.0:
                m = int(rng.integers(1, 3))
                p2 = rng.uniform(0.4, 0.9)
                H2 = H + m * hf + p2
                par2 = self.par(colour, common, {P_GFLOOR: 0.0, P_Z0: H, P_PARAPET: p2, P_PHOTO: photo})
                for k in (P_RELIEF, P_WALL, P_WALL_M):  # the setback's walls as the building's
                    par2[k] = par[k]
                self.box((bx0, by0, H), (bx1, by1, H2), MAT_BUILDING, par2)
                top = (bx0, by0, bx1, by1, H2)
        tx0, ty0, tx1, ty1, tz = top
        if rng.random() < 0.5 and tx1 - tx0 > 6 and ty1 - ty0 > 6:  # stair house
            w, d = rng.uniform(2.5, 3.5), rng.uniform(2.5, 3.5)
            cx, cy = (
                rng.uniform(tx0 + 1 + w / 2, tx1 - 1 - w / 2),
                rng.uniform(ty0 + 1 + d / 2, ty1 - 1 - d / 2),
            )
            p = self.par(self.colour(PANEL + PLASTER[:3], 0.1), {P_STYLE: 1, P_AXIS: int(rng.integers(4))})
            self.box(
                (cx - w / 2, cy - d / 2, tz),
                (cx + w / 2, cy + d / 2, tz + rng.uniform(2.4, 2.9)),
                MAT_ROOFBOX,
                p,
            )
        for _ in range(int(rng.integers(0, 5))):  # HVAC units
            w, d = rng.uniform(0.8, 2.5), rng.uniform(0.8, 2.5)
            if tx1 - tx0 < w + 2 or ty1 - ty0 < d + 2:
                continue
            cx, cy = (
                rng.uniform(tx0 + 1 + w / 2, tx1 - 1 - w / 2),
                rng.uniform(ty0 + 1 + d / 2, ty1 - 1 - d / 2),
            )
            p = self.par(self.colour([(0.55, 0.56, 0.57), (0.35, 0.36, 0.37), (0.6, 0.6, 0.55)], 0.05))
            self.box(
                (cx - w / 2, cy - d / 2, tz),
                (cx + w / 2, cy + d / 2, tz + rng.uniform(0.7, 1.6)),
                MAT_ROOFBOX,
                p,
            )

    def facade_details(
        self, par: np.ndarray, fp: tuple[float, float, float, float], floors: int, conf: dict
    ) -> None:
        """What stands out of a facade and what is set into it: openings recessed `relief` m (a range;
        the kernels cut the reveals), a string course at the first floor, on some buildings columns of
        balconies (slab and parapet) in front of the upper-floor windows, and on a `wall_photos` share of
        them brick walls cut from real photos. Drawn from the building's own seed, so the layout of the
        scene does not change with these details."""
        rng = np.random.default_rng(int(par[P_SEED]) * 7919 + 13)
        par[P_RELIEF] = rng.uniform(*conf["relief"])
        if self.walls is not None and len(self.walls) and rng.random() < conf.get("wall_photos", 0.0):
            k = int(rng.integers(len(self.walls)))
            par[P_WALL], par[P_WALL_M] = k, self.walls[k]
        x0, y0, x1, y1 = fp
        hg, hf, bay = par[P_GFLOOR], par[P_FLOOR], par[P_BAY]
        stone = self.par((0.55, 0.53, 0.5))
        ledge = rng.uniform(0.12, 0.25)
        faces = (  # (u axis start, u axis end, outward normal) of the four faces
            ((x0, y0), (x1, y0), (0.0, -1.0)),
            ((x1, y1), (x0, y1), (0.0, 1.0)),
            ((x0, y1), (x0, y0), (-1.0, 0.0)),
            ((x1, y0), (x1, y1), (1.0, 0.0)),
        )
        balconies = rng.random() < conf.get("balconies", 0.0)
        for a, b, (nx, ny) in faces:
            a, b = np.array(a), np.array(b)
            self.slab(a, b, nx, ny, ledge, hg - 0.05, hg + 0.15, stone)  # string course
            if not balconies or floors < 2:
                continue
            L = float(np.linalg.norm(b - a))
            n = max(1, int(L / bay))
            m = 0.5 * (L - n * bay)
            for bi in range(n):
                if rng.random() > 0.35:
                    continue
                c = m + (bi + 0.5) * bay
                e = (b - a) / L
                lo, hi = a + e * (c - 0.42 * bay), a + e * (c + 0.42 * bay)
                for fl in range(1, floors):
                    z = hg + fl * hf - 0.15
                    self.slab(lo, hi, nx, ny, 1.1, z, z + 0.15, stone)  # the balcony's slab
                    rail = (lo + np.array([nx, ny]) * 1.05, hi + np.array([nx, ny]) * 1.05)
                    self.slab(*rail, nx, ny, 0.05, z + 0.15, z + 1.0, self.par((0.2, 0.2, 0.21)))

    def slab(self, a, b, nx: float, ny: float, depth: float, z0: float, z1: float, par: np.ndarray) -> None:
        """A box along the facade segment a-b standing `depth` out of it (outward normal (nx, ny))."""
        p, q = np.asarray(a, float), np.asarray(b, float) + np.array([nx, ny]) * depth
        lo = (min(p[0], q[0]), min(p[1], q[1]), z0)
        hi = (max(p[0], q[0]), max(p[1], q[1]), z1)
        self.box(lo, hi, MAT_KERB, par)

    def car(self, cx: float, cy: float, axis: int) -> None:
        rng = self.rng
        L, W = rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.9)
        hb, hc = rng.uniform(0.9, 1.05), rng.uniform(0.4, 0.55)
        hx, hy = (L / 2, W / 2) if axis == 0 else (W / 2, L / 2)
        g = self.group()
        self.cars.append(g)
        paint = self.colour(CARS, 0.06)
        par = self.par(paint, {P_STYLE: 0, P_AXIS: axis})
        self.box((cx - hx, cy - hy, 0.0), (cx + hx, cy + hy, hb), MAT_CAR, par, g)
        off = rng.uniform(-0.1, 0.3) * L * (1 if rng.random() < 0.5 else -1) * 0.3
        cl, cw = 0.55 * L, W - 0.16
        ox, oy = (off, 0.0) if axis == 0 else (0.0, off)
        chx, chy = (cl / 2, cw / 2) if axis == 0 else (cw / 2, cl / 2)
        parc = self.par(paint, {P_STYLE: 1, P_AXIS: axis, P_R2: 0.03, P_G2: 0.035, P_B2: 0.045})
        self.box(
            (cx + ox - chx, cy + oy - chy, hb), (cx + ox + chx, cy + oy + chy, hb + hc), MAT_CAR, parc, g
        )

    def tree(self, x: float, y: float, small: bool = False) -> None:
        rng = self.rng
        g = self.group()
        r = rng.uniform(1.2, 2.0) if small else rng.uniform(1.6, 2.8)
        h = rng.uniform(2.4, 3.2) if small else rng.uniform(2.8, 3.8)
        bark = self.par((0.12, 0.09, 0.06))
        self.box((x - 0.15, y - 0.15, 0.0), (x + 0.15, y + 0.15, h + 0.5 * r), MAT_TRUNK, bark, g)
        leaf = self.colour(
            [(0.06, 0.14, 0.03), (0.09, 0.16, 0.04), (0.12, 0.15, 0.05), (0.05, 0.1, 0.04)], 0.1
        )
        self.sphere((x, y, h + 0.7 * r), r, MAT_CROWN, self.par(leaf), g)

    def bush(self, x: float, y: float) -> None:
        r = self.rng.uniform(0.5, 1.1)
        leaf = self.colour([(0.06, 0.13, 0.04), (0.1, 0.14, 0.05)], 0.1)
        self.sphere((x, y, 0.35 * r), r, MAT_BUSH, self.par(leaf), self.group())

    def lamp(self, x: float, y: float, nx: float, ny: float) -> None:
        g = self.group()
        p = self.par((0.08, 0.1, 0.09))
        self.box((x - 0.07, y - 0.07, 0.0), (x + 0.07, y + 0.07, 6.2), MAT_POLE, p, g)
        ex, ey = x + 1.2 * nx, y + 1.2 * ny
        lo = (min(x, ex) - 0.12, min(y, ey) - 0.12, 6.0)
        hi = (max(x, ex) + 0.12, max(y, ey) + 0.12, 6.2)
        self.box(lo, hi, MAT_POLE, self.par((0.5, 0.5, 0.48)), g)

    def kiosk(self, x: float, y: float, axis: int) -> None:
        w, d = (2.2, 1.6) if axis == 0 else (1.6, 2.2)
        p = self.par(
            self.colour([(0.5, 0.1, 0.05), (0.1, 0.3, 0.15), (0.1, 0.15, 0.45), (0.6, 0.5, 0.1)], 0.1)
        )
        self.box((x - w / 2, y - d / 2, 0.0), (x + w / 2, y + d / 2, 2.6), MAT_KIOSK, p, self.group())


def _split_lots(rect, lot_min: float, lot_max: float, rng: np.random.Generator) -> list[tuple]:
    x0, y0, x1, y1 = rect
    w, h = x1 - x0, y1 - y0
    if max(w, h) <= lot_max or max(w, h) < 2 * lot_min:
        return [rect]
    if w >= h:
        s = _snap(x0 + w * rng.uniform(0.4, 0.6), 0.5)
        s = min(max(s, x0 + lot_min), x1 - lot_min)
        return _split_lots((x0, y0, s, y1), lot_min, lot_max, rng) + _split_lots(
            (s, y0, x1, y1), lot_min, lot_max, rng
        )
    s = _snap(y0 + h * rng.uniform(0.4, 0.6), 0.5)
    s = min(max(s, y0 + lot_min), y1 - lot_min)
    return _split_lots((x0, y0, x1, s), lot_min, lot_max, rng) + _split_lots(
        (x0, s, x1, y1), lot_min, lot_max, rng
    )


def block_sides(b: dict) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
    """The 4 kerb lines of a block, counter-clockwise: (start (2,), tangent (2,), inward normal (2,),
    length)."""
    x0, y0, x1, y1 = b["x0"], b["y0"], b["x1"], b["y1"]
    return [
        (np.array([x0, y0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), x1 - x0),  # south side
        (np.array([x1, y0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), y1 - y0),  # east side
        (np.array([x1, y1]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), x1 - x0),  # north side
        (np.array([x0, y1]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), y1 - y0),  # west side
    ]


def _fill_lot(
    b: _Builder, blk: dict, lot: tuple, inner: tuple, conf: dict, rng: np.random.Generator, fill
) -> None:
    """One lot of a block: a building (set back from the lot's edges), or grass with trees and bushes,
    or a parking lot with rows of cars; its zone painted with `fill`."""
    lx0, ly0, lx1, ly1 = lot
    if rng.random() < conf["p_building"]:
        m = [
            rng.uniform(0.0, 0.8) if abs(v - w) < 1e-6 else rng.uniform(0.5, 2.5)
            for v, w in zip(lot, inner, strict=True)
        ]
        fp = (_snap(lx0 + m[0]), _snap(ly0 + m[1]), _snap(lx1 - m[2]), _snap(ly1 - m[3]))
        fill(*fp, Z_UNDER)
        b.building(fp, conf)
        blk["lots"].append({"rect": list(lot), "use": "building", "footprint": list(fp)})
        return
    use = "grass" if rng.random() < 0.6 else "parking"
    blk["lots"].append({"rect": list(lot), "use": use})
    fill(lx0 + 0.5, ly0 + 0.5, lx1 - 0.5, ly1 - 0.5, Z_GRASS if use == "grass" else Z_PARKING)
    if use == "grass":
        for _ in range(int(rng.integers(1, 4))):
            b.tree(rng.uniform(lx0 + 2.5, lx1 - 2.5), rng.uniform(ly0 + 2.5, ly1 - 2.5), small=True)
        for _ in range(int(rng.integers(2, 7))):
            b.bush(rng.uniform(lx0 + 1.5, lx1 - 1.5), rng.uniform(ly0 + 1.5, ly1 - 1.5))
        return
    y = ly0 + 3.0  # rows of parked cars along x
    while y < ly1 - 3.0:
        x = lx0 + 1.5
        while x < lx1 - 1.5:
            if rng.random() < 0.7 * conf["clutter"]:
                b.car(x, y, 1)
            x += 2.6
        y += 6.5


def _kerbs(b: _Builder, x0: float, y0: float, x1: float, y1: float) -> None:
    """The four kerbs of a block."""
    k = 0.2
    for lo, hi in (
        ((x0, y0, 0), (x1, y0 + k, 0.12)),
        ((x0, y1 - k, 0), (x1, y1, 0.12)),
        ((x0, y0 + k, 0), (x0 + k, y1 - k, 0.12)),
        ((x1 - k, y0 + k, 0), (x1, y1 - k, 0.12)),
    ):
        b.box(lo, hi, MAT_KERB, b.par((0.45, 0.44, 0.42)))


def _street_furniture(b: _Builder, blk: dict, conf: dict, sw: float, rng: np.random.Generator) -> None:
    """Along the 4 sides of a block: parked cars in the road's parking lane, street trees, lamps and
    now and then a kiosk."""
    for start, tan, nrm, length in block_sides(blk):
        axis = 0 if tan[0] != 0 else 1
        s = rng.uniform(4.0, 7.0)
        while s < length - 7.0:
            L = 5.2
            if rng.random() < 0.65 * conf["clutter"]:
                p = start + (s + L / 2) * tan - 1.2 * nrm
                b.car(p[0], p[1], axis)
            s += L + rng.uniform(0.3, 3.0)
        if rng.random() < 0.55:  # street trees
            s = rng.uniform(3.0, 8.0)
            while s < length - 3.0:
                p = start + s * tan + 0.9 * nrm
                b.tree(p[0], p[1])
                s += rng.uniform(8.0, 13.0)
        s = rng.uniform(5.0, 15.0)  # lamps
        while s < length - 3.0:
            p = start + s * tan + 0.45 * nrm
            b.lamp(p[0], p[1], -nrm[0], -nrm[1])
            s += rng.uniform(22.0, 28.0)
        if rng.random() < 0.25 * conf["clutter"]:  # kiosk
            p = start + rng.uniform(8.0, max(length - 8.0, 8.5)) * tan + (sw * 0.55) * nrm
            b.kiosk(p[0], p[1], axis)


def make_scene(
    conf: dict, rng: np.random.Generator, photo: bool = False, walls: np.ndarray | None = None
) -> Scene:
    """Generate the block grid of `conf` (see presets.py, key "scene"); photo: facades tiled with whole
    photos; walls: metres per pixel of the wall photos (services.synth.walls) that facade details may
    use."""
    nbx, nby = conf["blocks"]
    ctx = conf["context"]
    ntx, nty = nbx + 2 * ctx, nby + 2 * ctx
    Bx, By = (_snap(v, 0.5) for v in conf["block"])
    Rw, sw = _snap(conf["road"], 0.5), _snap(conf["sidewalk"], 0.5)
    Px, Py = Bx + Rw, By + Rw
    X0, Y0 = _snap(-(ntx * Px + Rw) / 2), _snap(-(nty * Py + Rw) / 2)
    Wz, Hz = int(round((ntx * Px + Rw) / ZONE_RES)), int(round((nty * Py + Rw) / ZONE_RES))
    zone = np.full((Hz, Wz), Z_ROAD, np.uint8)

    def fill(x0: float, y0: float, x1: float, y1: float, z: int) -> None:
        i0, i1 = int(round((x0 - X0) / ZONE_RES)), int(round((x1 - X0) / ZONE_RES))
        j0, j1 = int(round((y0 - Y0) / ZONE_RES)), int(round((y1 - Y0) / ZONE_RES))
        zone[max(j0, 0) : max(j1, 0), max(i0, 0) : max(i1, 0)] = z

    b = _Builder(rng, photo, walls)
    blocks = []
    for bj in range(nty):
        for bi in range(ntx):
            x0, y0 = X0 + bi * Px + Rw, Y0 + bj * Py + Rw
            x1, y1 = x0 + Bx, y0 + By
            surveyed = ctx <= bi < ctx + nbx and ctx <= bj < ctx + nby
            blk = {"i": bi, "j": bj, "x0": x0, "y0": y0, "x1": x1, "y1": y1, "surveyed": surveyed, "lots": []}
            blocks.append(blk)
            fill(x0, y0, x1, y1, Z_SIDEWALK)
            inner = (x0 + sw, y0 + sw, x1 - sw, y1 - sw)
            fill(*inner, Z_PAVED)
            for lot in _split_lots(inner, conf["lot_min"], conf["lot_max"], rng):
                _fill_lot(b, blk, lot, inner, conf, rng, fill)
            _kerbs(b, x0, y0, x1, y1)
            _street_furniture(b, blk, conf, sw, rng)
    xs0, ys0 = X0 + ctx * Px, Y0 + ctx * Py
    surveyed = np.array([xs0, ys0, xs0 + nbx * Px + Rw, ys0 + nby * Py + Rw])
    f8 = lambda a, n: np.asarray(a, np.float64).reshape(-1, n)  # noqa: E731
    return Scene(
        boxes=f8(b.boxes, 6),
        bmat=np.asarray(b.bmat, np.int64),
        bpar=f8(b.bpar, NPAR),
        bgroup=np.asarray(b.bgroup, np.int64),
        sph=f8(b.sph, 4),
        smat=np.asarray(b.smat, np.int64),
        spar=f8(b.spar, NPAR),
        sgroup=np.asarray(b.sgroup, np.int64),
        zone=zone,
        zmeta=np.array([X0, Y0, ZONE_RES]),
        lay=np.array([X0, Y0, Px, Py, Rw, ntx, nty, sw], np.float64),
        surveyed=surveyed,
        blocks=blocks,
        transient=_transient_cars(b.cars, conf.get("transient", 0.0), rng),
    )


def _transient_cars(cars: list[int], share: float, rng: np.random.Generator) -> dict[int, str]:
    """A `share` of the parked cars there in one capture only (half of them the flight's, half the
    ground walk's): drawn after the layout, so that it does not change with the share."""
    if share <= 0.0 or not cars:
        return {}
    draw = np.random.default_rng(rng.integers(2**31))
    out = {}
    for g in cars:
        x = draw.random()
        if x < share:
            out[g] = "aerial" if x < share / 2 else "ground"
    return out
