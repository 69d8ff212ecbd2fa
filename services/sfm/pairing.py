"""Image pairs for the aerial SfM, from the POS: exhaustive, spatial neighbours, or footprint overlap.

`pairs` (the mode):
- exhaustive: every pair;
- spatial: each image with its `num_neighbors` nearest POS positions (within `max_distance_m`);
- footprint: pairs whose ground footprints overlap by more than `footprint.min_overlap` (the
  intersection area over the smaller footprint). A footprint is the image rectangle (intrinsics prior)
  cast from the POS position and attitude onto a horizontal terrain plane; for oblique views it is cut
  where rays pass above the horizon and at `max_range_factor` flight heights ahead, so it stays a convex
  polygon (intersections by convex clipping, numpy only). Images without a POS attitude get their
  spatial neighbours instead.
- auto: exhaustive up to `exhaustive_max` images, else footprint when `min_attitude_fraction` of the
  images have an attitude and the terrain height is known, else spatial.

The terrain plane: `footprint.ground_h` (ellipsoidal height, metres), else the median camera height
minus `footprint.height_above_ground`, else the POS's own: the take-off height of DJI images
(GPS height minus XMP RelativeAltitude, PosRecord.rel_alt). Without any, footprints are unavailable.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from services.colmap_model import Camera
from services.conf import merge_conf
from services.pos import LocalFrame, PosRecord

logger = logging.getLogger("midview.sfm.pairing")

MODES = ("auto", "exhaustive", "spatial", "footprint")

default_conf: dict[str, Any] = {
    "pairs": "auto",
    "exhaustive_max": 50,  # images; auto matches smaller sets exhaustively
    "num_neighbors": 20,  # spatial
    "max_distance_m": 1.0e6,  # spatial
    "footprint": {
        "min_overlap": 0.1,  # intersection area / smaller footprint area
        "ground_h": None,  # terrain plane: ellipsoidal height (m) ...
        "height_above_ground": None,  # ... or median camera height minus this (m) ...
        "max_range_factor": 5.0,  # obliques: footprints end this many flight heights ahead
        "min_attitude_fraction": 0.9,  # auto: footprint when this share of images has an attitude
    },
}


# -- polygons ----------------------------------------------------------------------------------
def polygon_area(poly: np.ndarray) -> float:
    """Signed area (counter-clockwise positive) of a (N, 2) polygon."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def clip_halfplane(poly: np.ndarray, a: np.ndarray, c: float) -> np.ndarray:
    """The part of a convex (N, 2) polygon where a . p + c <= 0 (Sutherland-Hodgman, one edge)."""
    if len(poly) == 0:
        return poly
    s = poly @ a + c
    out = []
    for k in range(len(poly)):
        p, q, sp, sq = poly[k], poly[(k + 1) % len(poly)], s[k], s[(k + 1) % len(poly)]
        if sp <= 0:
            out.append(p)
        if (sp < 0 < sq) or (sq < 0 < sp):
            out.append(p + (q - p) * (sp / (sp - sq)))
    return np.array(out).reshape(-1, 2)


def intersect_convex(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Intersection of two convex polygons (clip p by each edge of q)."""
    if polygon_area(q) < 0:
        q = q[::-1]
    out = p
    for k in range(len(q)):
        e = q[(k + 1) % len(q)] - q[k]
        n = np.array([e[1], -e[0]])  # outward normal of a counter-clockwise edge
        out = clip_halfplane(out, n, -float(n @ q[k]))
        if len(out) == 0:
            break
    return out


def overlap(p: np.ndarray, q: np.ndarray) -> float:
    """Intersection area of two convex polygons over the area of the smaller one (0 when either is empty)."""
    ap, aq = abs(polygon_area(p)), abs(polygon_area(q))
    if min(ap, aq) <= 0:
        return 0.0
    return abs(polygon_area(intersect_convex(p, q))) / min(ap, aq)


# -- footprints --------------------------------------------------------------------------------
def footprint_polygon(
    center: np.ndarray,
    R_world_from_cam: np.ndarray,
    camera: Camera,
    ground_z: float,
    max_range_factor: float = 5.0,
    eps: float = 1e-3,
) -> np.ndarray | None:
    """(N, 2) convex ground polygon (counter-clockwise, x east, y north) of an image on z = ground_z.

    The image rectangle is clipped in the normalised image plane to the rays that go down (d_z <= -eps)
    and reach the plane within `max_range_factor` flight heights ahead (horizontally, along the optical
    axis); both limits are half-planes there, so the ground polygon stays convex. None when the camera is
    not above the plane or no ray reaches it.
    """
    height = float(center[2] - ground_z)
    if height <= 0:
        return None
    K = camera.K
    corners = np.array([[0.0, 0.0], [camera.width, 0.0], [camera.width, camera.height], [0.0, camera.height]])
    xy = (corners - K[:2, 2]) / np.diag(K)[:2]
    R = np.asarray(R_world_from_cam, float)
    # d(x, y) = R @ [x, y, 1]: each limit is a . (x, y) + c <= 0
    xy = clip_halfplane(xy, R[2, :2], float(R[2, 2]) + eps)
    fwd = R[:2, 2]
    if np.linalg.norm(fwd) > 1e-6:
        f = fwd / np.linalg.norm(fwd)
        row = f @ R[:2] + max_range_factor * R[2]  # (f . d_xy) + factor * d_z <= 0
        xy = clip_halfplane(xy, row[:2], float(row[2]))
    if len(xy) < 3:
        return None
    d = np.c_[xy, np.ones(len(xy))] @ R.T
    lam = (ground_z - center[2]) / d[:, 2]
    poly = center[None, :2] + lam[:, None] * d[:, :2]
    return poly if polygon_area(poly) > 0 else poly[::-1]


def terrain_z(records: dict[str, PosRecord], frame: LocalFrame, conf: dict) -> tuple[float | None, str]:
    """ENU height of the terrain plane and where it came from (None, reason when unknown)."""
    fc = conf["footprint"]
    if fc.get("ground_h") is not None:
        return float(frame.from_wgs84(frame.lat0, frame.lon0, float(fc["ground_h"]))[0][2]), "ground_h"
    enu = np.array([frame.from_wgs84(r.lat, r.lon, r.h)[0] for r in records.values()])
    if fc.get("height_above_ground") is not None:
        return float(np.median(enu[:, 2]) - float(fc["height_above_ground"])), "height_above_ground"
    takeoff = [(r.lat, r.lon, r.h - r.rel_alt) for r in records.values() if r.rel_alt is not None]
    if takeoff:
        t = np.array(takeoff)
        z = frame.from_wgs84(t[:, 0], t[:, 1], t[:, 2])[:, 2]
        return float(np.median(z)), "POS relative altitude"
    return None, "no terrain height (set footprint.ground_h or height_above_ground)"


def footprints(
    names: list[str],
    records: dict[str, PosRecord],
    frame: LocalFrame,
    cameras: dict[str, Camera],
    ground_z: float,
    max_range_factor: float = 5.0,
) -> dict[str, np.ndarray | None]:
    """{name: ground polygon or None (no attitude, no camera, not hitting the plane)}."""
    out: dict[str, np.ndarray | None] = {}
    for n in names:
        r, cam = records[n], cameras.get(n)
        if r.R_world_from_cam is None or cam is None:
            out[n] = None
            continue
        c = frame.from_wgs84(r.lat, r.lon, r.h)[0]
        R = frame.rotation_to_enu_at(r.lat, r.lon).T @ r.R_world_from_cam  # into the frame's ENU
        out[n] = footprint_polygon(c, R, cam, ground_z, max_range_factor)
    return out


# -- pairs -------------------------------------------------------------------------------------
def exhaustive_pairs(n: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def spatial_pairs(positions: np.ndarray, num_neighbors: int, max_distance: float) -> list[tuple[int, int]]:
    """Each index with its `num_neighbors` nearest positions within `max_distance`."""
    d = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    pairs = set()
    for i in range(len(positions)):
        for j in np.argsort(d[i])[1 : num_neighbors + 1]:
            if d[i, j] <= max_distance:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def footprint_pairs(polygons: list[np.ndarray | None], min_overlap: float) -> list[tuple[int, int, float]]:
    """(i, j, overlap) of the footprints overlapping by more than `min_overlap` (bounding boxes first)."""
    idx = [i for i, p in enumerate(polygons) if p is not None]
    if len(idx) < 2:
        return []
    boxes = np.array([[*polygons[i].min(0), *polygons[i].max(0)] for i in idx])  # type: ignore[union-attr]
    hit = (
        (boxes[:, None, 0] <= boxes[None, :, 2])
        & (boxes[None, :, 0] <= boxes[:, None, 2])
        & (boxes[:, None, 1] <= boxes[None, :, 3])
        & (boxes[None, :, 1] <= boxes[:, None, 3])
    )
    out = []
    for a, b in zip(*np.nonzero(np.triu(hit, 1)), strict=True):
        i, j = idx[a], idx[b]
        o = overlap(polygons[i], polygons[j])  # type: ignore[arg-type]
        if o > min_overlap:
            out.append((i, j, o))
    return out


def resolve_mode(conf: dict, n: int, records: dict[str, PosRecord], ground_z: float | None) -> str:
    """The pairing of `conf['pairs']`; auto picks exhaustive, footprint or spatial (module docstring)."""
    mode = conf["pairs"]
    if mode not in MODES:
        raise ValueError(f"unknown pairing {mode!r}: use one of {', '.join(MODES)}")
    if mode != "auto":
        return mode
    if n <= conf["exhaustive_max"]:
        return "exhaustive"
    with_att = sum(r.R_world_from_cam is not None for r in records.values()) / max(len(records), 1)
    if with_att >= conf["footprint"]["min_attitude_fraction"] and ground_z is not None:
        return "footprint"
    return "spatial"


def get_pairs(
    conf: dict,
    names: list[str],
    records: dict[str, PosRecord],
    frame: LocalFrame,
    cameras: dict[str, Camera],
) -> tuple[str, list[tuple[str, str]]]:
    """(mode, name pairs) of the images `names` (their POS in `records`, intrinsics priors in `cameras`)."""
    conf = merge_conf(default_conf, conf)
    ground_z, ground_source = terrain_z(records, frame, conf)
    mode = resolve_mode(conf, len(names), records, ground_z)
    positions = np.array([frame.from_wgs84(records[n].lat, records[n].lon, records[n].h)[0] for n in names])
    if mode == "exhaustive":
        idx = exhaustive_pairs(len(names))
    elif mode == "spatial":
        idx = spatial_pairs(positions, int(conf["num_neighbors"]), float(conf["max_distance_m"]))
    else:
        if ground_z is None:
            raise ValueError(f"footprint pairs: {ground_source}")
        fc = conf["footprint"]
        polys = footprints(names, records, frame, cameras, ground_z, float(fc["max_range_factor"]))
        found = footprint_pairs([polys[n] for n in names], float(fc["min_overlap"]))
        idx = [(i, j) for i, j, _ in found]
        missing = [i for i, n in enumerate(names) if polys[n] is None]
        if missing:  # no attitude or footprint: spatial neighbours instead
            near = spatial_pairs(positions, int(conf["num_neighbors"]), float(conf["max_distance_m"]))
            idx = sorted(set(idx) | {p for p in near if p[0] in missing or p[1] in missing})
        logger.info(
            "footprints on the terrain plane z = %.1f m (ENU, from %s): %d pairs over %.0f%% overlap, "
            "%d image(s) without a footprint",
            ground_z,
            ground_source,
            len(found),
            100 * float(fc["min_overlap"]),
            len(missing),
        )
    return mode, [(names[i], names[j]) for i, j in idx]


# -- in-plane rotations -------------------------------------------------------------------------
def quarter_turns(R_i: np.ndarray, R_j: np.ndarray) -> int:
    """Counter-clockwise quarter turns of image i (np.rot90) that align it in-plane with image j, from
    their attitudes (R_world_from_cam): the angle of j's image "down" axis seen in image i, rounded."""
    v = np.asarray(R_i).T @ np.asarray(R_j)[:, 1]
    return int(np.round(np.degrees(np.arctan2(-v[0], v[1])) / 90.0)) % 4


NORTH_UP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # a nadir camera, image top north


def upright_turns(records: dict[str, PosRecord], names: list[str]) -> dict[str, int]:
    """For features that are not rotation invariant (ALIKED, LightGlue): per image the quarter turns
    (np.rot90) that bring its view of the ground to "north up", from its POS attitude: a nadir image
    then has north at the top and an oblique one its heading's side of the ground, so images that
    overlap end up at about one in-plane orientation (a serpentine flight's lines are 180 degrees apart
    otherwise). One turn per image keeps one keypoint list per image. No attitude: no turn."""
    out = {}
    for n in names:
        R = records[n].R_world_from_cam
        out[n] = 0 if R is None else quarter_turns(R, NORTH_UP)
    return out


def write_pairs(path: str | Path, pairs: list[tuple[str, str]]) -> Path:
    """A pairs file, `name0 name1` per line (COLMAP's imported pairs, hloc's pairs.txt)."""
    path = Path(path)
    path.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    return path


def main(
    conf: dict,
    names: list[str],
    records: dict[str, PosRecord],
    frame: LocalFrame,
    cameras: dict[str, Camera],
    pairs_path: str | Path,
) -> Path:
    """Write the pairs of `get_pairs` to `pairs_path`; returns it."""
    mode, pairs = get_pairs(conf, names, records, frame, cameras)
    logger.info("%s pairing: %d pairs of %d images", mode, len(pairs), len(names))
    return write_pairs(pairs_path, pairs)
