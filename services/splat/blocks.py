"""Block-wise 3DGS refinement at the source resolution, for the intermediate views.

    plan = plan_blocks(confs["default"], model, rec, views)      # blocks from the planned views
    write_plan(plan, "job/blocks/plan.json")
    train_block(plan, "b00", model_path, rec, images, "job/blocks")  # one unit of work per block
    merged, ids = merge_blocks(load_model(model_path), "job/blocks")  # what the views render from
                                                                    # (services.views.BlockRenderer)

The whole-scene model, trained on downscaled aerial images, smears where the intermediate views look:
they stand two to four times nearer the facades than the aerial cameras. As in VastGaussian and
CityGaussian, the scene the views see is cut into blocks; each block is trained on its own, from the
crops of the full-resolution aerial images that see it (a camera with the crop's size and shifted
principal point), starting from the whole-scene Gaussians inside its box (the cell plus a margin). The
rest of the scene is rendered with it in every step but frozen, so what lies outside the box neither
smears into it nor is re-learnt. The trained blocks are merged as VastGaussian merges them: each
block's Gaussians inside its cell replace the whole-scene ones there (`merge_blocks`), and every view
renders from the merged model.

Blocks: each planned view's surface (its depth, rendered from the whole-scene model at `probe_width`
pixels, back-projected) gives samples; a grid on the ground plane (x, y) with cells of `block_px`
pixels of the aerial images at the source resolution (a crop of about that size sees a cell) holds
them; every cell with at least `min_share` of the samples is a block, and each view is covered by the
blocks that hold its samples.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import torch

from services.colmap_model import Camera, Pose
from services.conf import merge_conf
from services.geometry import pose_of_image, scaled_camera

from .model import sh_degree_of, splats_from_tensors
from .ply import load_ply, save_ply
from .projection import viewmat_from_pose
from .render import load_model, render

log = logging.getLogger("midview.splat.blocks")

confs: dict[str, dict[str, Any]] = {
    "default": {
        "block_px": 640,  # a block's extent, in pixels of the aerial images at the source resolution
        "probe_width": 64,  # width of the depth renders that find what a view (or aerial image) sees
        "min_share": 0.02,  # a grid cell with this share of the views' samples is a block
        "view_share": 0.1,  # a block covers the views with this share of their samples in its cell
        "margin_m": 2.0,  # a block trains the Gaussians this far outside its cell too (not kept)
        "max_images": 12,  # aerial images (crops) per block, those that see most of it
        "min_visible": 0.3,  # an image trains a block if it sees this fraction of its samples
        # a crop's longer side at most this (larger windows are downscaled): on `small` a 35 m block's
        # crops are 500-1100 px at the source resolution; 512 keeps a step at a third of a second on
        # 2 CPU cores, 2.4x finer than the whole-scene 3DGS at 400 px
        "max_crop_px": 512,
        "crop_margin_px": 24,
        "min_crop_px": 48,
        # training of one block (services.splat.train conf entries)
        "train": {
            "steps": 600,
            "sh_degree_interval": 0,  # the whole-scene model's degree from the start
            "depth_lambda": 0.1,
            "test_every": 0,
            "ckpt_every": 100,
            "log_every": 100,
            "save_test_renders": False,
            "strategy": {
                "refine_start_iter": 100,
                "refine_stop_iter": 400,
                "refine_every": 100,
                "reset_every": 1_000_000,  # no opacity reset: the Gaussians start trained
                "max_gaussians": 150_000,
            },
        },
    },
}


@dataclass
class Crop:
    """A window [x0, x1) x [y0, y1) of an aerial image at the source resolution, trained at `scale`."""

    image: str
    x0: int
    y0: int
    x1: int
    y1: int
    scale: float = 1.0

    @property
    def size(self) -> tuple[int, int]:
        w, h = self.x1 - self.x0, self.y1 - self.y0
        return max(1, round(w * self.scale)), max(1, round(h * self.scale))

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """K (3, 3) of the full image -> K of the crop at its training size (principal point shifted)."""
        K = np.asarray(K, float).copy()
        K[0, 2] -= self.x0
        K[1, 2] -= self.y0
        return np.diag([self.scale, self.scale, 1.0]) @ K

    @staticmethod
    def limits(K: np.ndarray, width: int, height: int) -> tuple[float, ...]:
        """The projection's Jacobian bounds of the full image (K, width, height): a crop rendered with
        them equals the window of the full render (projection.jacobian_limits)."""
        from .projection import jacobian_limits

        return tuple(
            float(v) for v in jacobian_limits(torch.as_tensor(K, dtype=torch.float64), width, height)
        )


@dataclass
class Block:
    """One unit of training: its cell (lo, hi: the box whose Gaussians it replaces), the margin around
    the cell it trains too, the views whose samples it holds and its training crops."""

    id: str
    lo: list[float]
    hi: list[float]
    views: list[str]
    crops: list[Crop] = field(default_factory=list)
    samples: int = 0
    margin: float = 0.0
    reason: str | None = None  # why it cannot be trained (the whole-scene model stays in its cell)

    def inside(self, xyz: np.ndarray | torch.Tensor, margin: float = 0.0):
        """Whether points (N, 3) lie in the cell (grown by `margin` metres)."""
        lo = np.asarray(self.lo, float) - margin
        hi = np.asarray(self.hi, float) + margin
        if torch.is_tensor(xyz):
            lo, hi = torch.as_tensor(lo, dtype=xyz.dtype), torch.as_tensor(hi, dtype=xyz.dtype)
        return ((xyz >= lo) & (xyz <= hi)).all(-1)


# -- planning ---------------------------------------------------------------------------------------
def surface_samples(model, camera: Camera, pose: Pose, width: int, backend: str = "auto") -> np.ndarray:
    """(M, 3) world points where `camera` at `pose` sees the model's surface (alpha >= 0.5), at `width`."""
    cam = scaled_camera(camera, width)
    out = render(model, cam, pose, backend=backend)
    v, u = np.nonzero((out["alpha"] >= 0.5) & (out["depth"] > 0))
    if len(u) == 0:
        return np.zeros((0, 3))
    uv = np.stack([u + 0.5, v + 0.5], 1).astype(float)  # pixel centres (COLMAP convention)
    return pose.unproject(np.asarray(cam.K, float), uv, out["depth"][v, u].astype(float))


def grid_cells(samples: np.ndarray, size: float, min_share: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cells (lo, hi) of a grid of `size` metres on the ground plane over `samples` (N, 3) holding at
    least `min_share` of them, most samples first; each cell's height spans its samples (1st to 99th
    percentile)."""
    origin = samples[:, :2].min(0)
    ij = np.floor((samples[:, :2] - origin) / size).astype(int)
    keys, inverse, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    cells = []
    for k in np.argsort(-counts, kind="stable"):
        if counts[k] < min_share * len(samples):
            break
        z = samples[inverse == k, 2]
        lo = np.r_[origin + keys[k] * size, np.percentile(z, 1.0)]
        hi = np.r_[origin + (keys[k] + 1) * size, np.percentile(z, 99.0)]
        cells.append((lo, hi))
    return cells


def source_gsd(rec: pycolmap.Reconstruction, max_points: int = 20_000) -> float:
    """Median metres per pixel of the aerial images at the source resolution, at the SfM points inside
    each image."""
    xyz = np.array([p.xyz for p in rec.points3D.values()], float).reshape(-1, 3)
    xyz = xyz[:: max(1, len(xyz) // max_points)]
    gsd = []
    for img in rec.images.values():
        if not img.has_pose or not len(xyz):
            continue
        cam = Camera.from_pycolmap(img.camera)
        uv, z = pose_of_image(img).project(np.asarray(cam.K, float), xyz)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if ok.any():
            gsd.append(float(np.median(z[ok])) / float(np.mean(np.diag(cam.K)[:2])))
    if not gsd:
        raise ValueError("no aerial image sees any SfM point: cannot size the blocks")
    return float(np.median(gsd))


class AerialProbe:
    """The aerial images of a model, with low-resolution depth renders for visibility (cached)."""

    def __init__(self, model, rec: pycolmap.Reconstruction, width: int, backend: str = "auto"):
        self.model, self.width, self.backend = model, width, backend
        self.images = {
            img.name: (Camera.from_pycolmap(img.camera), pose_of_image(img))
            for img in rec.images.values()
            if img.has_pose
        }
        self._depth: dict[str, tuple[np.ndarray, float]] = {}

    def depth(self, name: str) -> tuple[np.ndarray, float]:
        """(depth (h, w) at `width`, its scale against the source resolution)."""
        if name not in self._depth:
            cam, pose = self.images[name]
            small = scaled_camera(cam, max(self.width * 4, 128))
            out = render(self.model, small, pose, backend=self.backend)
            self._depth[name] = (out["depth"], small.width / cam.width)
        return self._depth[name]

    def visible(self, name: str, xyz: np.ndarray, tol: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """Source-resolution pixels (M, 2) of the points `xyz` image `name` sees unoccluded, and the mask."""
        cam, pose = self.images[name]
        uv, z = pose.project(np.asarray(cam.K, float), xyz)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        depth, s = self.depth(name)
        iu = np.clip((uv[:, 0] * s).astype(int), 0, depth.shape[1] - 1)
        iv = np.clip((uv[:, 1] * s).astype(int), 0, depth.shape[0] - 1)
        d = depth[iv, iu]
        ok &= (d <= 0) | (z <= d * (1.0 + tol) + 0.5)
        return uv[ok], ok


def choose_crops(conf: dict, probe: AerialProbe, pts: np.ndarray) -> list[Crop]:
    """The crops of the aerial images that see most of the points `pts` (at most conf["max_images"])."""
    found = []
    for name, (cam, _) in probe.images.items():
        uv, ok = probe.visible(name, pts)
        if ok.mean() < conf["min_visible"]:
            continue
        lo = np.percentile(uv, 1.0, axis=0) - conf["crop_margin_px"]
        hi = np.percentile(uv, 99.0, axis=0) + conf["crop_margin_px"]
        x0, y0 = (int(max(0, np.floor(v))) for v in lo)
        x1, y1 = int(min(cam.width, np.ceil(hi[0]))), int(min(cam.height, np.ceil(hi[1])))
        if min(x1 - x0, y1 - y0) < conf["min_crop_px"]:
            continue
        scale = min(1.0, conf["max_crop_px"] / max(x1 - x0, y1 - y0))
        found.append((float(ok.mean()), Crop(name, x0, y0, x1, y1, round(scale, 4))))
    found.sort(key=lambda t: (-t[0], t[1].image))
    return [c for _, c in found[: conf["max_images"]]]


def plan_blocks(
    conf: dict, model, rec: pycolmap.Reconstruction, views: list[dict], backend: str = "auto"
) -> dict:
    """Blocks for the planned `views` (views.json entries: name, camera, pose): see the module docstring.
    Returns {"conf", "gsd_m", "block_m", "blocks": [Block as dict], "uncovered": [views no block holds]}."""
    conf = merge_conf(confs["default"], conf)
    samples = {}
    for v in views:
        pose = Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float))
        pts = surface_samples(model, Camera(**v["camera"]), pose, conf["probe_width"], backend)
        if len(pts):
            samples[v["name"]] = pts
    gsd = source_gsd(rec)
    size = conf["block_px"] * gsd
    probe = AerialProbe(model, rec, conf["probe_width"], backend)
    every = np.concatenate(list(samples.values())) if samples else np.zeros((0, 3))
    blocks = []
    for i, (lo, hi) in enumerate(grid_cells(every, size, conf["min_share"]) if len(every) else []):
        b = Block(f"b{i:02d}", lo.tolist(), hi.tolist(), [], margin=float(conf["margin_m"]))
        held = {n: float(b.inside(pts).mean()) for n, pts in samples.items()}
        b.views = sorted(n for n, share in held.items() if share >= conf["view_share"])
        pts = every[b.inside(every)]
        b.samples = len(pts)
        b.crops = choose_crops(conf, probe, pts[:: max(1, len(pts) // 4000)])
        if not b.crops:
            b.reason = "no aerial image sees this block"
        blocks.append(b)
    covered = {n for b in blocks for n in b.views}
    uncovered = sorted(v["name"] for v in views if v["name"] not in covered)
    log.info(
        "%d blocks of %.1f m (%d px at %.3f m per pixel) for %d views (%d not covered), %s crops",
        len(blocks), size, conf["block_px"], gsd, len(views), len(uncovered), [len(b.crops) for b in blocks],
    )  # fmt: skip
    return {
        "conf": conf,
        "gsd_m": gsd,
        "block_m": size,
        "blocks": [asdict(b) for b in blocks],
        "uncovered": uncovered,
    }


def write_plan(plan: dict, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(plan, indent=1))
    return path


def read_blocks(path: str | Path) -> list[Block]:
    plan = json.loads(Path(path).read_text())
    return [Block(**{**b, "crops": [Crop(**c) for c in b["crops"]]}) for b in plan["blocks"]]


# -- training ---------------------------------------------------------------------------------------
def crop_views(block: Block, rec: pycolmap.Reconstruction, images: Path):
    """Training views (services.splat.train.View) of a block's crops, with their sparse-depth targets."""
    from .train import View, load_image, sparse_depth

    by_name = {img.name: img for img in rec.images.values()}
    views = []
    for crop in block.crops:
        img = by_name[crop.image]
        cam = Camera.from_pycolmap(img.camera)
        K = crop.intrinsics(cam.K)
        w, h = crop.size
        pose = Pose.of_image(img)
        full = load_image(images / crop.image, cam.width, cam.height)
        window = full[crop.y0 : crop.y1, crop.x0 : crop.x1].permute(2, 0, 1)[None]
        pixels = torch.nn.functional.interpolate(window, size=(h, w), mode="area")[0].permute(1, 2, 0)
        v = View(f"{crop.image}@{crop.x0},{crop.y0}", torch.tensor(K, dtype=torch.float32),
                 viewmat_from_pose(pose.R, pose.t), w, h, pixels.contiguous())  # fmt: skip
        ids = [p.point3D_id for p in img.points2D if p.has_point3D()]
        xyz = np.array([rec.points3D[i].xyz for i in ids], float).reshape(-1, 3)
        v.depth_pixels, v.depth_targets = sparse_depth(xyz, K, pose, w, h)
        v.limits = Crop.limits(cam.K, cam.width, cam.height)
        views.append(v)
    return views


@torch.no_grad()
def reaching(model: dict[str, torch.Tensor], views) -> dict[str, torch.Tensor]:
    """The Gaussians of `model` that can reach any of `views` (projection.frustum_candidates): the rest
    never touch a training crop, so a block's frozen background need not carry them."""
    from .model import activated
    from .projection import frustum_candidates

    if not len(model["means"]):
        return model
    p = activated(model)
    hit = torch.zeros(len(p["means"]), dtype=torch.bool)
    for v in views:
        ids = frustum_candidates(
            p["means"], p["scales"], p["opacities"], v.viewmat, v.K, v.width, v.height, limits=v.limits
        )
        hit[ids] = True
    return {k: t[hit] for k, t in model.items()}


def split_model(model: dict[str, torch.Tensor], block: Block, margin: float = 0.0) -> tuple[dict, dict]:
    """(the Gaussians inside the block's cell grown by `margin`, the rest) of a model (model.py layout)."""
    inside = block.inside(model["means"].detach(), margin)
    return (
        {k: v.detach()[inside] for k, v in model.items()},
        {k: v.detach()[~inside] for k, v in model.items()},
    )


def block_digest(plan: dict, block: Block, model_path: Path) -> str:
    """What a block's checkpoints were made from: its plan entry, the training conf and the whole-scene
    model file's contents (so a block resumes only from checkpoints of the same inputs)."""
    h = hashlib.sha256(json.dumps([asdict(block), plan["conf"]["train"]], sort_keys=True).encode())
    model_path = Path(model_path)
    if model_path.is_dir():
        model_path = model_path / "point_cloud.ply"
    with open(model_path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _finished(folder: Path, digest: str) -> dict | None:
    """block.json's figures when the block was finished from the same inputs (digest); else None,
    block.json removed and the checkpoints too when they were made from other inputs."""
    done = folder / "block.json"
    if done.is_file():
        doc = json.loads(done.read_text())
        if doc.get("digest") == digest and (not doc["trained"] or (folder / "point_cloud.ply").is_file()):
            return doc
    done.unlink(missing_ok=True)
    stamp = folder / "inputs.sha256"
    if not stamp.is_file() or stamp.read_text().strip() != digest:
        shutil.rmtree(folder / "ckpts", ignore_errors=True)
        stamp.write_text(digest + "\n")
    return None


def train_block(
    plan_path: str | Path,
    block_id: str,
    model_path: str | Path,
    sparse: str | Path,
    images: str | Path,
    out: str | Path,
    backend: str = "auto",
    report: Callable[[float, str], None] | None = None,
) -> dict:
    """Train one block of a plan (plan.json of `plan_blocks`) into OUT/<id>/ (point_cloud.ply: the
    block's Gaussians; block.json: figures) in chunks of `ckpt_every` steps, reporting each. Resumes from
    OUT/<id>/ckpts when they were made from the same inputs; returns block.json's figures (at once when
    the block is done already)."""
    from .train import SceneData, Trainer

    plan = json.loads(Path(plan_path).read_text())
    block = next(b for b in read_blocks(plan_path) if b.id == block_id)
    folder = Path(out) / block_id
    folder.mkdir(parents=True, exist_ok=True)
    if block.reason:
        return _untrained(folder, block, block.reason)
    digest = block_digest(plan, block, Path(model_path))
    finished = _finished(folder, digest)
    if finished is not None:
        return finished
    t0 = time.perf_counter()
    model = load_model(model_path)
    own, rest = split_model(model, block, block.margin)
    if not len(own["means"]):  # nothing to refine (densification grows only from existing Gaussians)
        return _untrained(folder, block, "the whole-scene 3DGS has no Gaussian in this block", digest)
    rec = pycolmap.Reconstruction(str(sparse))
    views = crop_views(block, rec, Path(images))
    rest = reaching(rest, views)
    data = SceneData(views, np.zeros((0, 3)), np.zeros((0, 3)), list(range(len(views))), [])
    conf = merge_conf(plan["conf"]["train"], {"sh_degree": sh_degree_of(model), "seed": int(block_id[1:])})
    trainer = Trainer(conf, data, folder, backend, init=own, frozen=rest)
    before = trainer_psnr(trainer, own)
    chunk = max(1, int(trainer.conf["ckpt_every"]))

    def emptied() -> bool:
        return trainer.splats is not None and not len(trainer.splats["means"])

    while trainer.step < trainer.total_steps and not emptied():
        trainer.train(resume=True, stop_after=min(trainer.step + chunk, trainer.total_steps), progress=False)
        if report is not None:
            report(
                trainer.step / trainer.total_steps,
                f"block {block_id}: step {trainer.step}/{trainer.total_steps}",
            )
    if emptied():  # pruned to nothing: its cell keeps the whole-scene model
        return _untrained(folder, block, f"its training pruned every Gaussian (step {trainer.step})", digest)
    save_ply(trainer.splats, folder / "point_cloud.ply")
    doc = {
        "id": block_id,
        "trained": True,
        "views": block.views,
        "crops": len(views),
        "pixels": int(sum(v.width * v.height for v in views)),
        "steps": trainer.step,
        "gaussians_before": int(len(own["means"])),
        "gaussians": int(len(trainer.splats["means"])),
        "frozen": int(len(rest["means"])),
        "psnr_before": before,
        "psnr_after": trainer_psnr(trainer),
        "seconds": time.perf_counter() - t0,
        "digest": digest,
    }
    tmp = folder / "block.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(folder / "block.json")
    log.info(
        "block %s: %d crops, %d -> %d Gaussians, crop PSNR %.2f -> %.2f dB, %.0f s",
        block_id, doc["crops"], doc["gaussians_before"], doc["gaussians"], before, doc["psnr_after"],
        doc["seconds"],
    )  # fmt: skip
    return doc


def _untrained(folder: Path, block, reason: str, digest: str | None = None) -> dict:
    """block.json of a block left to the whole-scene model (its views render from that), and why."""
    (folder / "point_cloud.ply").unlink(missing_ok=True)
    doc = {"id": block.id, "trained": False, "reason": reason, "views": block.views}
    if digest is not None:
        doc["digest"] = digest
    (folder / "block.json").write_text(json.dumps(doc, indent=1))
    return doc


@torch.no_grad()
def trainer_psnr(trainer, splats: dict | None = None) -> float:
    """Mean PSNR over the trainer's views, of its model or of `splats` (model.py layout)."""
    from .loss import psnr

    saved = trainer.splats
    if splats is not None:
        trainer.splats = splats_from_tensors(splats, requires_grad=False).to(trainer.device)
    try:
        vals = [psnr(trainer.render_view(v)[0].clamp(0, 1).cpu(), v.image) for v in trainer.data.views]
    finally:
        trainer.splats = saved
    return float(np.mean(vals)) if vals else float("nan")


# -- merging ---------------------------------------------------------------------
def merge_blocks(model: dict[str, torch.Tensor], blocks_dir: str | Path) -> tuple[dict, list[str]]:
    """The whole-scene `model` with each trained block's Gaussians inside its cell in place of its own
    there (VastGaussian's merge); returns (the merged model, the ids of the blocks merged)."""
    blocks_dir = Path(blocks_dir)
    trained = [
        b for b in read_blocks(blocks_dir / "plan.json")
        if not b.reason and (blocks_dir / b.id / "point_cloud.ply").is_file()
    ]  # fmt: skip
    means = model["means"].detach()
    keep = torch.ones(len(means), dtype=torch.bool)
    parts = []
    for b in trained:
        keep &= ~b.inside(means)
        own = load_ply(blocks_dir / b.id / "point_cloud.ply")
        sel = b.inside(own["means"].detach())
        parts.append({k: v.detach()[sel] for k, v in own.items()})
    merged = {k: torch.cat([v.detach()[keep], *(p[k] for p in parts)]) for k, v in model.items()}
    return merged, [b.id for b in trained]
