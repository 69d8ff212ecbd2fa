"""The combined SfM's last adjustment: the ground images tied to other ground images by their own points
refined against all their observations, the aerial images held where the aerial SfM and its georeference
put them.

The mapper holds the frames of its input model fixed: the aerial images, and the ground images seeded at
the reducer's PnP pose. A seed's PnP pose rests on the rendered views' points alone and can be decimetres
off within its stated std (on `small-walk` one seed 0.51 m off, 114 inliers); held fixed, it places the
ground-ground points it triangulates and with them every ground image the mapper registers through them
(a run of 8 images 0.5-0.8 m off, docs/measurements.md). Released in a bundle adjustment with the aerial
images held, it moves to where the transferred aerial points and its neighbours' observations agree.
A robust loss keeps the wrong transferred matches that survived the reducer from pulling; ground images
that share too few points with other ground images stay held (a lone image's pose is its PnP pose, or the
mapper's, on the same transferred matches).
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from services.pose_uncertainty import held_adjustment

logger = logging.getLogger("midview.combined_sfm")


def _chained_ground(rec: pycolmap.Reconstruction, min_shared: int) -> dict[int, str]:
    """{image id: name} of the registered ground images that observe at least `min_shared` 3D points
    another ground image observes too: those the ground images' own pairs tie to their neighbours."""
    shared: dict[int, int] = {}
    for p in rec.points3D.values():
        ids = {e.image_id for e in p.track.elements if rec.images[e.image_id].name.startswith("ground/")}
        if len(ids) >= 2:
            for i in ids:
                shared[i] = shared.get(i, 0) + 1
    return {i: rec.images[i].name for i, n in shared.items() if n >= min_shared and rec.images[i].has_pose}


def refine_ground(
    rec: pycolmap.Reconstruction, conf: dict, among: set[str] | None = None
) -> dict[str, float]:
    """Bundle-adjust `rec` in place with its aerial frames, intrinsics and the ground images that share
    fewer than min_shared_observations points with other ground images held (a lone image's PnP pose
    rests on the same transferred matches, chosen by RANSAC; freed, its 2-view aerial-ground points let
    it slide: on `small` one moved from 0.03 to 0.37 m off), and, with `among`, every ground image not
    named there; the rest of the ground images and every 3D point free.
    Returns {ground image name: how far its camera centre moved (m)}."""
    free = _chained_ground(rec, int(conf["min_shared_observations"]))
    if among is not None:
        free = {i: n for i, n in free.items() if n in among}
    if not free:
        return {}
    before = {i: np.asarray(rec.images[i].projection_center()) for i in free}
    for _ in range(int(conf["rounds"])):
        cfg, opts = held_adjustment(rec, free)
        opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, str(conf["loss"]).upper())
        opts.ceres.loss_function_scale = float(conf["loss_scale_px"])
        opts.ceres.solver_options.max_num_iterations = int(conf["max_iterations"])
        summary = pycolmap.create_default_bundle_adjuster(opts, cfg, rec).solve()
        filtered = pycolmap.ObservationManager(rec).filter_all_points3D(
            float(conf["max_reproj_px"]), float(conf["min_tri_angle_deg"])
        )
        logger.info(
            "ground refinement: %d ground images free, %s, %d observations filtered",
            len(free),
            summary.termination_type.name,
            filtered,
        )
    return {
        name: float(np.linalg.norm(np.asarray(rec.images[i].projection_center()) - before[i]))
        for i, name in free.items()
    }
