"""Combined aerial + ground reconstruction, seeded with the aerial model (services.sfm.combined).

Database (out/database.db), a copy of the aerial SfM database with:
- the aerial images' keypoints extended: the aerial SfM keypoints first (their indices, matches and
  the aerial model's tracks stay valid), then the matching features (services.matching.features cache) the
  transferred matches refer to, at an offset;
- the ground camera, the ground images with their matching features and their POS as pose priors;
- ground-ground matches (POS neighbours, the matching features, an essential-matrix RANSAC whose
  relative pose must agree with the POS, and its rotation with the images' attitudes tied to the aerial
  images where the reducer's PnP ties both: facades repeat, and a fundamental matrix alone verified pairs
  that share nothing) and the transferred aerial-ground matches (the reducer's verified matches), with
  two-view geometries.

Input model (out/input): the aerial model rebuilt with the extended keypoints (with `seed_pnp_poses`
also the ground images whose PnP pose the reducer accepted, held at that pose: by default those whose
pose rests on rendered depth the reducer trusted), and one 3D point per
transferred track, triangulated from its observations in registered images; the keypoints of the other
ground images link a track's aerial observations without being part of it. pycolmap's incremental mapper
continues from it (`input_path`): it registers the other ground images through these points,
triangulates, and bundle-adjusts everything; ground images it registered but the model leaves uncertain
(their own points do not count for more than the aerial points that place them) or far from their POS
are dropped, and those the reducer localized are added at their PnP pose where the mapper left them out.
Before that the ground images their own pairs chain are refined with the aerial images held
(`refine_ground`: the seeds too).
The result is georeferenced like the aerial model (a similarity to the aerial POS in the aerial model's
ENU frame) and written to out/sparse with report.json (NRI per set, N3P, reprojection error, ground
camera positions against the PnP and POS).

Modules: `database` (the combined database), `model` (the input model), `mapping` (the mapper, the
dropped and added ground images), `refine` (the last adjustment), `blocks` (chains of ground images the
mapper left out, placed together on their ties), `report`, `confs`; `main` runs them as named steps.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap

from services.colmap_model import Camera, read_cameras_json
from services.conf import merge_conf
from services.pos import DEFAULT_STD_XY
from services.sfm.aerial import colmap_log_level
from services.sfm.combined.blocks import place_blocks
from services.sfm.combined.confs import default_conf
from services.sfm.combined.database import (
    CombinedDatabase,
    build_database,
    ground_pairs,
    verify_ground_pair,
    write_ground,
    write_pair,
)
from services.sfm.combined.mapping import add_pnp_images, drop_ill_determined, run_mapper, settle_ground
from services.sfm.combined.model import (
    build_input_model,
    registered_ground,
    rests_on_trusted_depth,
    seed_tracks,
)
from services.sfm.combined.report import build_report, write_gis
from services.sfm.combined.surface import SurfaceCheck
from services.sfm.combined.surface import default_conf as surface_conf
from shared.logging import stage

logger = logging.getLogger("midview.combined_sfm")

confs = {"default": default_conf}

__all__ = [
    "CombinedDatabase",
    "SurfaceCheck",
    "surface_conf",
    "seed_tracks",
    "write_ground",
    "write_pair",
    "add_pnp_images",
    "build_input_model",
    "build_report",
    "confs",
    "default_conf",
    "drop_ill_determined",
    "ground_pairs",
    "main",
    "registered_ground",
    "rests_on_trusted_depth",
    "verify_ground_pair",
]


def georeference(rec: pycolmap.Reconstruction, aerial_dir: Path, pos: str | Path, conf: dict):
    """Georeference the combined model like the aerial one (a similarity to the aerial POS in the aerial
    model's ENU frame), unless its aerial images were held fixed: (frame, summary or None)."""
    from services.pos import read_pos
    from services.sfm import georef as georef_mod

    frame = georef_mod.read_georef_frame(aerial_dir / "georef.json")
    if not conf["georef"] or conf["mapping"]["fix_aerial"]:
        return frame, None
    records = {r.name: r for r in read_pos(pos) if r.name.startswith("aerial/")}
    sigma = float(np.median([r.std_or_default()[0] for r in records.values()])) if records else DEFAULT_STD_XY
    try:
        geo = georef_mod.georeference(rec, records, frame, sigma)
        return frame, {**georef_mod.summary(geo), "method": geo.method}
    except georef_mod.GeorefError as e:
        logger.warning("georeferencing failed: %s", e)
        return frame, None


def write_model(rec: pycolmap.Reconstruction, out: Path) -> Path:
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    rec.write(str(out))
    return out


def main(
    conf: dict | None,
    aerial_dir: str | Path,
    transfer_dir: str | Path,
    feature_path: str | Path,
    match_conf: dict,
    image_dir: str | Path,
    pos: str | Path,
    cameras: str | Path | dict[str, Camera],
    out_dir: str | Path,
    progress=None,
) -> Path:
    """Build the combined database and model; returns out_dir/sparse. `aerial_dir` is the aerial SfM
    output (database.db, sparse/, georef.json), `transfer_dir` the reducer's (matches.h5,
    ground_poses.json), `feature_path` the matching features' cache and `match_conf` the matching conf
    (services.matching.views) for the ground-ground pairs."""
    from services.reduce import default_conf as reduce_conf

    conf = merge_conf(default_conf, conf)
    aerial_dir, transfer_dir, out_dir = Path(aerial_dir), Path(transfer_dir), Path(out_dir)
    image_dir = Path(image_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cams = read_cameras_json(cameras) if isinstance(cameras, str | Path) else dict(cameras)
    prog = progress or (lambda f, m: None)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}

    with stage("combined:database", logger):
        t0 = time.perf_counter()
        cdb = build_database(
            aerial_dir, transfer_dir, out_dir, image_dir, Path(feature_path), cams["ground"], pos,
            match_conf, conf, lambda f, m: prog(0.6 * f, m),
        )  # fmt: skip
        timings["database"] = time.perf_counter() - t0

    with stage("combined:input-model", logger):
        aerial = pycolmap.Reconstruction(str(aerial_dir / "sparse"))
        pnp = json.loads((transfer_dir / "ground_poses.json").read_text())["images"]
        seed = build_input_model(
            aerial, cdb.path, cdb.ids, cdb.offsets, cdb.ag, pnp, cdb.pair_sizes, conf, out_dir / "input"
        )

    with stage("combined:mapping", logger), colmap_log_level(conf["colmap_log_level"]) as warnings:
        t0 = time.perf_counter()
        n_ids = len(cdb.ids)
        step = lambda f, m: prog(0.6 + 0.35 * f, m)  # noqa: E731
        rec = run_mapper(cdb.path, image_dir, out_dir, seed, n_ids, conf, step)
        timings["mapping"] = time.perf_counter() - t0
        limits = conf["pos_limits"] or reduce_conf["pnp"]
        dropped, added, refined = settle_ground(rec, seed, cdb, pnp, limits, conf)
        blocks = place_blocks(rec, cdb, image_dir, out_dir / "blocks", conf, limits)

    with stage("combined:georef", logger):
        frame, geo_summary = georeference(rec, aerial_dir, pos, conf)
        sparse = write_model(rec, out_dir / "sparse")
        shutil.copy(aerial_dir / "georef.json", out_dir / "georef.json")

    fixed, min_pair = conf["mapping"]["fix_aerial"], int(conf["mapping"]["min_num_matches"])
    report = build_report(
        rec, cdb.ids, cdb.priors, pnp, seed, geo_summary, timings, t_all, added, dropped, fixed,
        cdb.pair_sizes, min_pair, refined, cdb.ground_pairs, [b.to_dict() for b in blocks],
    )  # fmt: skip
    report["ground_pairs"] = cdb.ground_pairs
    report["colmap_warnings"] = warnings  # the solver's warnings, counted (not printed line by line)
    if conf["gis"]:
        with stage("combined:gis", logger):
            report["gis"] = write_gis(rec, frame, pos, report, aerial_dir, out_dir / "gis")
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    logger.info(
        "combined model: NRI aerial %s, ground %s; N3P %d; reprojection error %.2f px -> %s",
        report["NRI"]["aerial"],
        report["NRI"]["ground"],
        report["num_points3D"],
        report["mean_reprojection_error_px"],
        sparse,
    )
    prog(1.0, "done")
    return sparse
