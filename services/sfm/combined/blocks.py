"""Chains of ground images the mapper left out, placed as one block each.

A walk's images tie each other by hundreds of verified ground-ground matches, but each may reach the
aerial model through too few points for the mapper to localize it alone (12-18 verified ties an image at
one end of `isprs-walk`). Pooled, a chain's ties can place it: the chain is reconstructed on its own
(pycolmap's incremental mapper on its images, in a frame of its own), and a similarity maps it into the
aerial model's frame where the chain's points meet the model's points: the aerial points their
transferred matches reach, and the points of the registered ground images they share a verified pair
with (the walk's images next to the chain, hundreds of matches at a few metres' range) (LO-RANSAC,
pycolmap.estimate_sim3d_robust). A block is placed only when ties of at least two of its
images agree (one image's matches alone can all be a repeated facade shifted by a window) and each of its
cameras then agrees with its POS; its images join the model at those poses, observing the aerial points
their matches reach and the block's own points, and are refined with the aerial images held.

    placed = place_blocks(rec, cdb, image_dir, out_dir / "blocks", conf["blocks"], pos_limits)

Shapes: ties (N, 3) points in the block's frame and in the model's.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from services.colmap_model import Pose
from services.geometry import pose_of_image
from services.sfm.combined.database import CombinedDatabase
from services.sfm.combined.mapping import add_at_poses, drop_ill_determined, mapper_options
from services.sfm.combined.refine import refine_ground

logger = logging.getLogger("midview.combined_sfm")


@dataclass
class Block:
    """One chain's reconstruction and where it went: `names` the chain, `model` its own reconstruction,
    `ties` (agreeing, all), the images whose ties agree, the similarity model_from_block and the images
    placed (or the reason none was)."""

    names: list[str]
    model: pycolmap.Reconstruction | None = None
    ties: tuple[int, int] = (0, 0)
    tie_images: list[str] = field(default_factory=list)
    sim: pycolmap.Sim3d | None = None
    placed: list[str] = field(default_factory=list)
    reason: str = ""

    def to_dict(self) -> dict:
        return {
            "images": self.names,
            "reconstructed": 0 if self.model is None else int(self.model.num_reg_images()),
            "ties": {"agreeing": self.ties[0], "all": self.ties[1], "images": self.tie_images},
            "scale": None if self.sim is None else float(self.sim.scale),
            "placed": self.placed,
            "reason": self.reason or "ok",
        }


def unregistered_chains(
    rec: pycolmap.Reconstruction, cdb: CombinedDatabase, min_images: int
) -> list[list[str]]:
    """The connected groups of at least `min_images` ground images that `rec` leaves unregistered, joined
    by their verified ground-ground pairs (cdb.ground_pairs), each sorted, in name order."""
    registered = {im.name for im in rec.images.values() if im.has_pose}
    out = {g for g in cdb.ids if g.startswith("ground/") and g not in registered}
    links: dict[str, set[str]] = {g: set() for g in out}
    for key, r in cdb.ground_pairs.items():
        a, b = key.split(" ", 1)
        if r.get("accepted") and a in links and b in links:
            links[a].add(b)
            links[b].add(a)
    seen: set[str] = set()
    chains = []
    for g in sorted(links):
        if g in seen:
            continue
        chain, todo = set(), [g]
        while todo:
            x = todo.pop()
            if x not in chain:
                chain.add(x)
                todo += links[x] - chain
        seen |= chain
        if len(chain) >= min_images:
            chains.append(sorted(chain))
    return chains


def reconstruct_chain(
    db_path: Path,
    image_dir: Path,
    out_dir: Path,
    names: list[str],
    mapping: pycolmap.IncrementalPipelineOptions,
) -> pycolmap.Reconstruction | None:
    """The chain's own reconstruction from the combined database's pairs among `names` (the largest model
    of pycolmap's incremental mapper), or None."""
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    mapping.image_names = list(names)
    models = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(out_dir), mapping)
    return max(models.values(), key=lambda r: r.num_reg_images()) if models else None


def chain_ties(
    block: pycolmap.Reconstruction, rec: pycolmap.Reconstruction, cdb: CombinedDatabase
) -> tuple[np.ndarray, np.ndarray, list[tuple[str, int, int]]]:
    """(Y (N, 3) block points, X (N, 3) model points, each tie's (ground image, its keypoint, the model
    point's id)): a block image's keypoint with a block point, matched to a keypoint with a model point:
    an aerial keypoint its transferred matches reach (cdb.ag), or a registered ground image's keypoint
    through their verified ground-ground pair (neighbour_matches)."""
    in_block = {im.name: im for im in block.images.values() if im.has_pose}
    Y, X, who = [], [], []
    for other, g, m in [*cdb.ag, *neighbour_matches(in_block, rec, cdb)]:
        bim, oid = in_block.get(g), cdb.ids.get(other, -1)
        oim = rec.images[oid] if oid in rec.images else None
        if bim is None or oim is None or not oim.has_pose:
            continue
        offset = cdb.offsets.get(other, 0)
        for io, ig in m:
            po, pg = oim.points2D[int(io) + offset], bim.points2D[int(ig)]
            if po.has_point3D() and pg.has_point3D():
                X.append(rec.points3D[po.point3D_id].xyz)
                Y.append(block.points3D[pg.point3D_id].xyz)
                who.append((g, int(ig), int(po.point3D_id)))
    return np.reshape(Y, (-1, 3)), np.reshape(X, (-1, 3)), who


def neighbour_matches(
    in_block: dict[str, pycolmap.Image], rec: pycolmap.Reconstruction, cdb: CombinedDatabase
) -> list[tuple[str, str, np.ndarray]]:
    """[(registered ground image, block image, (M, 2) their keypoint indices)]: the inlier matches of the
    verified ground-ground pairs (cdb.ground_pairs) between a block image and a ground image `rec` holds
    registered, read from the combined database."""
    registered = {im.name for im in rec.images.values() if im.has_pose and im.name.startswith("ground/")}
    pairs = []
    for key, r in cdb.ground_pairs.items():
        a, b = key.split(" ", 1)
        if r.get("accepted"):
            if a in in_block and b in registered:
                pairs.append((b, a))
            elif b in in_block and a in registered:
                pairs.append((a, b))
    if not pairs:
        return []
    db = pycolmap.Database.open(str(cdb.path))
    try:
        return [
            (o, g, np.asarray(db.read_two_view_geometry(cdb.ids[o], cdb.ids[g]).inlier_matches, np.int64))
            for o, g in pairs
        ]
    finally:
        db.close()


def observe_ties(rec: pycolmap.Reconstruction, ties: list[tuple[str, int, int]], ids: dict[str, int]) -> int:
    """The placed images observe the model points of their agreeing ties (keypoints with no point yet,
    one observation of a point per image): what holds the block where its ties put it when it is
    refined. Returns how many."""
    n = 0
    for g, k, pid in ties:
        im = rec.images[ids[g]]
        if not im.has_pose or im.points2D[k].has_point3D():
            continue
        if any(e.image_id == im.image_id for e in rec.points3D[pid].track.elements):
            continue
        rec.add_observation(pid, pycolmap.TrackElement(im.image_id, k))
        n += 1
    return n


def fit_block(Y: np.ndarray, X: np.ndarray, conf: dict) -> tuple[pycolmap.Sim3d | None, np.ndarray]:
    """(model_from_block or None, the agreeing ties' mask): LO-RANSAC of a similarity on the ties."""
    if len(Y) < max(3, int(conf["min_ties"])):
        return None, np.zeros(len(Y), bool)
    opts = pycolmap.RANSACOptions(max_error=float(conf["tie_max_m"]))
    opts.random_seed = int(conf["seed"])
    res = pycolmap.estimate_sim3d_robust(Y, X, opts)
    if res is None:
        return None, np.zeros(len(Y), bool)
    return res["tgt_from_src"], np.asarray(res["inlier_mask"], bool)


def ties_reason(ties: tuple[int, int], tie_images: list[str], bc: dict) -> str:
    """Why a block's ties (agreeing, all) through `tie_images` do not place it ("": they do), by the
    "blocks" conf `bc`."""
    if ties[0] >= int(bc["min_ties"]) and len(tie_images) >= int(bc["min_tie_images"]):
        return ""
    return (
        f"{ties[0]} of {ties[1]} ties agree, through {len(tie_images)} of its images (at least "
        f"{bc['min_ties']} through {bc['min_tie_images']} needed)"
    )


def block_pose(image: pycolmap.Image, sim: pycolmap.Sim3d) -> Pose:
    """The pose (cam_from_world) in the model's frame of a block image (sim: model_from_block)."""
    pose = pose_of_image(image)
    R_sim = np.asarray(sim.rotation.matrix())
    R = pose.R @ R_sim.T
    C = float(sim.scale) * R_sim @ pose.center + np.asarray(sim.translation).ravel()
    return Pose(R, -R @ C)


def add_block_points(
    rec: pycolmap.Reconstruction, block: pycolmap.Reconstruction, sim: pycolmap.Sim3d, placed: set[int]
) -> int:
    """The block's own points in `rec` (model frame), observed by its placed images' keypoints that have
    no point yet; points left with fewer than two observations are skipped. Returns how many."""
    n = 0
    for p in block.points3D.values():
        elements = [
            pycolmap.TrackElement(e.image_id, e.point2D_idx)
            for e in p.track.elements
            if e.image_id in placed and not rec.images[e.image_id].points2D[e.point2D_idx].has_point3D()
        ]
        if len({e.image_id for e in elements}) < 2:
            continue
        rec.add_point3D(sim * p.xyz, pycolmap.Track(elements), p.color)
        n += 1
    return n


def place_chain(
    names: list[str],
    rec: pycolmap.Reconstruction,
    cdb: CombinedDatabase,
    image_dir: Path,
    out_dir: Path,
    conf: dict,
    pos_limits: dict,
) -> Block:
    """One chain reconstructed, fitted to the model by its ties and added to `rec` at those poses where
    each camera agrees with its POS (conf: the combined SfM's; its "blocks" section decides)."""
    from services.reduce import prior_agreement

    bc = conf["blocks"]
    b = Block(names)
    b.model = reconstruct_chain(cdb.path, image_dir, out_dir, names, mapper_options(conf["mapping"]))
    if b.model is None or b.model.num_reg_images() < int(bc["min_images"]):
        b.reason = "the chain's own reconstruction holds too few of its images"
        return b
    Y, X, who = chain_ties(b.model, rec, cdb)
    sim, agree = fit_block(Y, X, bc)
    b.ties = (int(agree.sum()), len(Y))
    b.tie_images = sorted({w[0] for w, ok in zip(who, agree, strict=True) if ok})
    b.reason = "" if sim is not None else "no similarity fits its ties"
    b.reason = b.reason or ties_reason(b.ties, b.tie_images, bc)
    if b.reason:
        return b
    b.sim = sim
    poses, off_pos = {}, {}
    for im in b.model.images.values():
        if not im.has_pose:
            continue
        pose = block_pose(im, sim)
        prior = cdb.priors.get(im.name)
        why = prior_agreement(pose, prior, cdb.prior_std.get(im.name), pos_limits)[2] if prior else []
        if why:
            off_pos[im.name] = "; ".join(why)
        else:
            poses[im.name] = {"R": pose.R.tolist(), "t": pose.t.tolist()}
    named = "; ".join(f"{n}: {w}" for n, w in off_pos.items())
    if len(poses) < int(bc["min_images"]):
        b.reason = f"{len(off_pos)} of {len(poses) + len(off_pos)} cameras disagree with their POS ({named})"
        return b
    b.placed = add_at_poses(rec, poses, cdb.path, cdb.ids, cdb.offsets, cdb.ag, conf)
    observe_ties(rec, [w for w, ok in zip(who, agree, strict=True) if ok and w[0] in poses], cdb.ids)
    add_block_points(rec, b.model, sim, {cdb.ids[g] for g in b.placed})
    if off_pos:
        b.reason = f"placed but for {len(off_pos)} cameras that disagree with their POS ({named})"
    return b


def drop_alone_undetermined(
    rec: pycolmap.Reconstruction, names: set[str], max_std: float | None
) -> dict[str, str]:
    """Deregister the images of `names` whose centre the model leaves undetermined even with every other
    image held (joint_position_stds of the image alone: an edge image whose points only its neighbour
    sees makes the block's joint covariance singular, and would take the block's other images with it
    in drop_ill_determined). Returns {name: reason}."""
    from services.pose_uncertainty import joint_position_stds

    if not max_std:
        return {}
    out = {}
    for im in [im for im in rec.images.values() if im.name in names and im.has_pose]:
        std = (joint_position_stds(rec, [im.image_id]) or {}).get(im.image_id, float("inf"))
        if not std <= max_std:
            rec.deregister_frame(im.frame_id)
            out[im.name] = f"position ill-determined with the rest of the model held (std {std:.2f} m)"
    return out


def place_blocks(
    rec: pycolmap.Reconstruction,
    cdb: CombinedDatabase,
    image_dir: Path,
    out_dir: Path,
    conf: dict,
    pos_limits: dict,
) -> list[Block]:
    """Each chain of unregistered ground images placed as a block (place_chain), then its images refined
    with the rest of the model held and dropped where the model leaves them uncertain or off their POS
    (drop_ill_determined). Updates `rec`; returns the blocks (conf: the combined SfM's)."""
    bc = conf["blocks"]
    chains = unregistered_chains(rec, cdb, int(bc["min_images"])) if bc["enabled"] else []
    blocks = [
        place_chain(c, rec, cdb, image_dir, out_dir / Path(c[0]).stem, conf, pos_limits) for c in chains
    ]
    placed = {g for b in blocks for g in b.placed}
    if not placed:
        return blocks
    if conf["refine_ground"]["enabled"]:
        refine_ground(rec, conf["refine_ground"], among=placed)
    max_std = conf["max_position_std_m"]
    dropped = drop_alone_undetermined(rec, placed, max_std)
    others = {im.name for im in rec.images.values() if im.has_pose and im.name not in placed}
    dropped |= drop_ill_determined(rec, others, max_std, cdb.priors, cdb.prior_std, pos_limits)
    for b in blocks:
        gone = [g for g in b.placed if g in dropped]
        if gone:
            b.placed = [g for g in b.placed if g not in dropped]
            b.reason = "; ".join([*filter(None, [b.reason]), *(f"{g} dropped: {dropped[g]}" for g in gone)])
        logger.info(
            "block of %d ground images (%s..%s): %d ties agree of %d through %d images; %d placed (%s)",
            len(b.names), b.names[0], b.names[-1], b.ties[0], b.ties[1], len(b.tie_images), len(b.placed),
            b.reason or "ok",
        )  # fmt: skip
    return blocks
