"""The combined SfM's report (NRI per set, N3P, reprojection error, each ground image's registration and
the reason of those not registered) and its GIS outputs."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from services.colmap_model import Pose
from services.sfm.combined.model import registered_ground

logger = logging.getLogger("midview.combined_sfm")


# why a ground image stayed out, one named cause each (report.json "cause", the GIS layers, the dashboard)
CAUSES = {
    "no-aerial-view": "its views show almost nothing that the aerial images see",
    "views-without-ties": "its views gave no aerial tie",
    "ties-without-pose": "aerial ties or pairs with registered images, too few or too weak for a pose",
    "chained-to-unregistered": "verified pairs only with ground images that are not registered",
    "ambiguous": "a pose was found, but it disagrees with its POS, is ill-determined or competes with a"
    " second pose its matches fit alike, so it was dropped",
}
MIN_VIEW_AERIAL_FRACTION = 0.1  # a view coloured from the aerial images over less than this shows them little


def _min_ties() -> int:
    """Aerial ties that count: the PnP inliers the reducer takes for a consensus (fewer are chance)."""
    from services.reduce import default_conf

    return int(default_conf["pnp"]["min_inliers"])


def cause_of(g: str, entry: dict, pnp: dict, partners: list[str], registered: set[str]) -> str:
    """The named cause (CAUSES) of a ground image that is not registered: `entry` its report entry,
    `pnp` its record of the reducer's ground_poses.json ({} when none; its ties: the PnP's inliers),
    `partners` the ground images of its verified ground-ground pairs, `registered` the registered
    images."""
    if entry.get("dropped") or pnp.get("accepted"):
        return "ambiguous"
    if int(pnp.get("num_inliers") or 0) >= _min_ties() or any(p in registered for p in partners):
        return "ties-without-pose"
    if partners:
        return "chained-to-unregistered"
    if pnp.get("views", 1) == 0 or float(pnp.get("view_aerial_fraction", 1.0)) < MIN_VIEW_AERIAL_FRACTION:
        return "no-aerial-view"
    return "views-without-ties"


def _ground_entry(
    g: str,
    reg: dict[str, pycolmap.Image],
    how: dict[str, str],
    priors: dict[str, Pose],
    pnp: dict[str, dict],
    dropped: dict[str, str],
    largest: int | None,
    min_pair_matches: int,
    refined_m: float | None = None,
) -> dict[str, Any]:
    """One ground image in the report: how it was registered and where (against its POS and PnP pose),
    or why it was not (`how`: "pnp" or "block" by name, else the mapper; `largest`: its largest verified
    pair; None: unknown)."""
    d: dict[str, Any] = {"registered": g in reg}
    if g in reg:
        # "pnp": from the reducer's PnP pose (seeded, kept fixed by the mapper, or added after it); "block":
        # with its chain, placed on the chain's ties (services.sfm.combined.blocks)
        d["registered_by"] = how.get(g, "mapper")
        if refined_m is not None:  # how far the last adjustment moved it (services.sfm.combined.refine)
            d["refined_m"] = refined_m
        d["observations"] = int(reg[g].num_points3D)
        c = np.asarray(reg[g].projection_center())
        d["center"] = c.tolist()
        if g in priors:
            d["to_pos_m"] = float(np.linalg.norm(c - priors[g].center))
        if pnp.get(g, {}).get("accepted"):
            d["to_pnp_m"] = float(np.linalg.norm(c - np.asarray(pnp[g]["center"], float)))
    elif g in dropped:
        d["dropped"] = True
        d["reason"] = f"registered by the mapper but dropped: {dropped[g]}"
    elif pnp.get(g, {}).get("accepted"):
        d["reason"] = "registered by PnP but dropped by the mapper"
    elif largest is not None and largest >= min_pair_matches:
        d["reason"] = (
            f"verified pairs (the largest {largest} matches), but too few of its matches reach"
            " 3D points of the registered images for the mapper to localize it"
        )
    else:
        d["reason"] = (
            "no verified aerial-ground or ground-ground pair of at least"
            f" {min_pair_matches} matches to register it"
        )
    return d


def build_report(
    rec: pycolmap.Reconstruction,
    ids: dict[str, int],
    priors: dict[str, Pose],
    pnp: dict[str, dict],
    seed: pycolmap.Reconstruction,
    georef: dict | None,
    timings: dict,
    t_all: float,
    added: list[str] | None = None,
    dropped: dict[str, str] | None = None,
    conf_fixed: bool = True,
    pair_sizes: dict[int, int] | None = None,
    min_pair_matches: int = 15,
    refined: dict[str, float] | None = None,
    ground_pairs: dict[str, dict] | None = None,
    blocks: list[dict] | None = None,
) -> dict:
    """report.json of the combined model (see the module docstring); each ground image left out with its
    named cause (cause_of; `ground_pairs`: the verified ground-ground pairs' records by "g0 g1"; `blocks`:
    Block.to_dict() of the chains placed as blocks)."""
    reg = {im.name: im for im in rec.images.values() if im.has_pose}
    # held at the PnP pose: added after the mapper, or seeded (unless the mapper's BA refined them)
    by_pnp = set(added or []) | (registered_ground(seed) if conf_fixed else set())
    how = {**{g: "pnp" for g in by_pnp}, **{g: "block" for b in blocks or [] for g in b["placed"]}}
    sets = {
        "aerial": sorted(n for n in ids if n.startswith("aerial/")),
        "ground": sorted(n for n in ids if n.startswith("ground/")),
    }
    ground = {
        g: _ground_entry(
            g,
            reg,
            how,
            priors,
            pnp,
            dropped or {},
            None if pair_sizes is None else pair_sizes.get(ids[g], 0),
            min_pair_matches,
            (refined or {}).get(g),
        )
        for g in sets["ground"]
    }
    partners: dict[str, list[str]] = {}
    for key, r in (ground_pairs or {}).items():
        if r.get("accepted"):
            a, b = key.split(" ", 1)
            partners.setdefault(a, []).append(b)
            partners.setdefault(b, []).append(a)
    for g, d in ground.items():
        if not d["registered"]:
            d["cause"] = cause_of(g, d, pnp.get(g, {}), partners.get(g, []), set(reg))
    causes = [d["cause"] for d in ground.values() if "cause" in d]
    return {
        "NRI": {s: f"{sum(n in reg for n in names)}/{len(names)}" for s, names in sets.items()},
        "num_registered": {s: sum(n in reg for n in names) for s, names in sets.items()},
        "num_images": {s: len(names) for s, names in sets.items()},
        "num_points3D": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "added_pnp_ground_images": sorted(added or []),
        "seeded_ground_images": len(registered_ground(seed)),
        "refined_ground_images": len(refined or {}),
        "blocks": blocks or [],
        "georef": georef,
        "ground": ground,
        "causes": {c: causes.count(c) for c in CAUSES if c in causes},
        "timings_s": {
            **{k: round(v, 2) for k, v in timings.items()},
            "total": round(time.perf_counter() - t_all, 2),
        },
    }


def write_gis(rec, frame, pos, report: dict, aerial_dir: Path, out: Path) -> dict:
    """GeoPackage, GeoJSON, omega/phi/kappa and LAS outputs (services.sfm.gis) in the aerial SfM's output
    CRS (else the POS CRS, else UTM); a failure is logged and reported, the model stays."""
    from services.pos import read_pos
    from services.sfm import gis

    try:
        crs_doc = json.loads((aerial_dir / "georef.json").read_text()).get("crs") or {}
        records = {r.name: r for r in read_pos(pos)}
        return gis.main(rec, frame, records, report, out, crs_doc.get("output") or crs_doc.get("pos"))
    except Exception as e:  # noqa: BLE001 - the reconstruction is the result; its exports are extras
        logger.warning("GIS outputs not written: %s", e)
        return {"error": f"{type(e).__name__}: {e}"}
