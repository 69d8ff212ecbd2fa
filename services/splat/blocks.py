"""Block-wise 3DGS refinement at the source resolution, for the intermediate views.

    plan = plan_blocks(confs["default"], model, rec, views)      # blocks from the planned views
    write_plan(plan, "job/blocks/plan.json")
    train_block(plan, "b00", model_path, rec, images, "job/blocks")  # one unit of work per block
    renderer = BlockRenderer(model_path, "job/blocks")             # each camera from the block that sees it

The whole-scene model, trained on downscaled aerial images, smears where the intermediate views look:
they stand two to four times nearer the facades than the aerial cameras. As in VastGaussian and
CityGaussian, the scene the views see is cut into blocks; each block is trained on its own, from the
crops of the full-resolution aerial images that see it (a camera with the crop's size and shifted
principal point), starting from the whole-scene Gaussians inside its box. The rest of the scene is
rendered with it in every step but frozen, so what lies outside the box neither smears into it nor is
re-learnt. A view renders from the block whose box holds most of what it sees (the whole-scene model
outside that box, the block's Gaussians inside).

Blocks: each planned view's surface (its depth, rendered from the whole-scene model at `probe_width`
pixels, back-projected) gives samples; the views are split recursively along the longer horizontal
axis of their samples' extent (at the median of the views' targets) until a block's extent is at most
`block_px` pixels of the aerial images at the source resolution (a crop of about that size sees all
of it). Every planned view belongs to exactly one block.
"""

from __future__ import annotations

import json
import logging
import time
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
        "box_percentile": 5.0,  # a block's box: these percentiles of its samples (per axis), plus margin
        "margin_m": 2.0,
        "max_images": 12,  # aerial images (crops) per block, those that see most of it
        "min_visible": 0.3,  # an image trains a block if it sees this fraction of its samples
        "max_crop_px": 768,  # a crop's longer side at most this (larger windows are downscaled)
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
    """One unit of training: the box its Gaussians lie in, the views it owns and its training crops."""

    id: str
    lo: list[float]
    hi: list[float]
    views: list[str]
    crops: list[Crop] = field(default_factory=list)
    samples: int = 0
    reason: str | None = None  # why it cannot be trained (then its views render from the whole scene)

    def inside(self, xyz: np.ndarray | torch.Tensor):
        lo, hi = (torch.as_tensor(x, dtype=xyz.dtype) if torch.is_tensor(xyz) else np.asarray(x)
                  for x in (self.lo, self.hi))  # fmt: skip
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


def box_of(samples: np.ndarray, percentile: float, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo = np.percentile(samples, percentile, axis=0) - margin
    hi = np.percentile(samples, 100.0 - percentile, axis=0) + margin
    return lo, hi


def split_views(
    names: list[str], samples: dict[str, np.ndarray], extent_m: float, percentile: float
) -> list[list[str]]:
    """Recursive bisection of views (by their samples' median) until each group's horizontal extent
    (percentiles of its samples) is at most `extent_m`, or it holds one view."""
    pts = np.concatenate([samples[n] for n in names])
    lo, hi = box_of(pts, percentile, 0.0)
    span = (hi - lo)[:2]
    if len(names) < 2 or span.max() <= extent_m:
        return [names]
    axis = int(np.argmax(span))
    centre = {n: float(np.median(samples[n][:, axis])) for n in names}
    order = sorted(names, key=lambda n: (centre[n], n))
    half = len(order) // 2
    return split_views(order[:half], samples, extent_m, percentile) + split_views(
        order[half:], samples, extent_m, percentile
    )


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
    Returns {"conf", "gsd_m", "blocks": [Block as dict]}."""
    conf = merge_conf(confs["default"], conf)
    samples = {}
    for v in views:
        pose = Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float))
        pts = surface_samples(model, Camera(**v["camera"]), pose, conf["probe_width"], backend)
        if len(pts):
            samples[v["name"]] = pts
    gsd = source_gsd(rec)
    extent = conf["block_px"] * gsd
    probe = AerialProbe(model, rec, conf["probe_width"], backend)
    blocks = []
    groups = split_views(sorted(samples), samples, extent, conf["box_percentile"]) if samples else []
    for i, names in enumerate(groups):
        pts = np.concatenate([samples[n] for n in names])
        lo, hi = box_of(pts, conf["box_percentile"], conf["margin_m"])
        keep = ((pts >= lo) & (pts <= hi)).all(1)
        sub = pts[keep][:: max(1, int(keep.sum()) // 4000)]
        b = Block(f"b{i:02d}", lo.tolist(), hi.tolist(), names, samples=int(keep.sum()))
        b.crops = choose_crops(conf, probe, sub)
        if not b.crops:
            b.reason = "no aerial image sees this block"
        blocks.append(b)
    blind = sorted(v["name"] for v in views if v["name"] not in samples)
    if blind:  # views that see nothing of the model: one block that cannot be trained, for the record
        blocks.append(
            Block(f"b{len(blocks):02d}", [0.0] * 3, [0.0] * 3, blind, reason="the view sees no surface")
        )
    log.info(
        "%d blocks for %d views (%.1f m each at most: %d px at %.3f m per pixel), %s crops",
        len(blocks), len(views), extent, conf["block_px"], gsd, [len(b.crops) for b in blocks],
    )  # fmt: skip
    return {"conf": conf, "gsd_m": gsd, "blocks": [asdict(b) for b in blocks]}


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
        m = img.cam_from_world().matrix()
        full = load_image(images / crop.image, cam.width, cam.height)
        window = full[crop.y0 : crop.y1, crop.x0 : crop.x1].permute(2, 0, 1)[None]
        pixels = torch.nn.functional.interpolate(window, size=(h, w), mode="area")[0].permute(1, 2, 0)
        v = View(f"{crop.image}@{crop.x0},{crop.y0}", torch.tensor(K, dtype=torch.float32),
                 viewmat_from_pose(m[:, :3], m[:, 3]), w, h, pixels.contiguous())  # fmt: skip
        ids = [p.point3D_id for p in img.points2D if p.has_point3D()]
        xyz = np.array([rec.points3D[i].xyz for i in ids], float).reshape(-1, 3)
        v.depth_pixels, v.depth_targets = sparse_depth(xyz, K, m, w, h)
        v.limits = Crop.limits(cam.K, cam.width, cam.height)
        views.append(v)
    return views


def split_model(model: dict[str, torch.Tensor], block: Block) -> tuple[dict, dict]:
    """(the Gaussians inside the block's box, the rest) of a model (model.py layout)."""
    inside = block.inside(model["means"].detach())
    return (
        {k: v.detach()[inside] for k, v in model.items()},
        {k: v.detach()[~inside] for k, v in model.items()},
    )


def train_block(
    plan_path: str | Path,
    block_id: str,
    model_path: str | Path,
    sparse: str | Path,
    images: str | Path,
    out: str | Path,
    backend: str = "auto",
    resume: bool = True,
) -> dict:
    """Train one block of a plan (plan.json of `plan_blocks`) into OUT/<id>/ (point_cloud.ply: the
    block's Gaussians; block.json: figures). Resumes from OUT/<id>/ckpts. Returns the figures."""
    from .train import SceneData, Trainer

    plan = json.loads(Path(plan_path).read_text())
    block = next(b for b in read_blocks(plan_path) if b.id == block_id)
    folder = Path(out) / block_id
    folder.mkdir(parents=True, exist_ok=True)
    if block.reason:
        doc = {"id": block_id, "trained": False, "reason": block.reason, "views": block.views}
        (folder / "block.json").write_text(json.dumps(doc, indent=1))
        return doc
    t0 = time.perf_counter()
    model = load_model(model_path)
    own, rest = split_model(model, block)
    rec = pycolmap.Reconstruction(str(sparse))
    views = crop_views(block, rec, Path(images))
    data = SceneData(views, np.zeros((0, 3)), np.zeros((0, 3)), list(range(len(views))), [])
    conf = merge_conf(plan["conf"]["train"], {"sh_degree": sh_degree_of(model), "seed": int(block_id[1:])})
    trainer = Trainer(conf, data, folder, backend, init=own, frozen=rest)
    before = trainer_psnr(trainer, own)
    trainer.train(resume=resume, progress=False)
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
    }
    (folder / "block.json").write_text(json.dumps(doc, indent=1))
    log.info(
        "block %s: %d crops, %d -> %d Gaussians, crop PSNR %.2f -> %.2f dB, %.0f s",
        block_id, doc["crops"], doc["gaussians_before"], doc["gaussians"], before, doc["psnr_after"],
        doc["seconds"],
    )  # fmt: skip
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


# -- rendering --------------------------------------------------------------------------------------
class BlockRenderer:
    """Renders each camera from the trained block whose box holds most of what the camera sees (the
    whole-scene model outside that box, the block's Gaussians inside), else from the whole-scene model."""

    name = "splat-blocks"

    def __init__(self, model_path: str | Path, blocks_dir: str | Path, backend: str = "auto", min_alpha=0.5):
        self.model = load_model(model_path)
        self.blocks_dir = Path(blocks_dir)
        self.blocks = [
            b for b in read_blocks(self.blocks_dir / "plan.json")
            if not b.reason and (self.blocks_dir / b.id / "point_cloud.ply").exists()
        ]  # fmt: skip
        self.backend, self.min_alpha = backend, float(min_alpha)
        self.probe_width = int(json.loads((self.blocks_dir / "plan.json").read_text())["conf"]["probe_width"])
        self._composed: dict[str, dict] = {}
        self.used: dict[str, int] = {}

    def owner(self, camera: Camera, pose: Pose) -> Block | None:
        pts = surface_samples(self.model, camera, pose, self.probe_width, self.backend)
        if not len(pts) or not self.blocks:
            return None
        counts = [int(b.inside(pts).sum()) for b in self.blocks]
        best = int(np.argmax(counts))
        return self.blocks[best] if counts[best] > 0 else None

    def composed(self, block: Block) -> dict:
        if block.id not in self._composed:
            _, rest = split_model(self.model, block)
            own = load_ply(self.blocks_dir / block.id / "point_cloud.ply")
            self._composed = {block.id: {k: torch.cat([own[k].detach(), rest[k]]) for k in rest}}
        return self._composed[block.id]

    def render(self, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        block = self.owner(camera, pose)
        model = self.model if block is None else self.composed(block)
        key = "whole" if block is None else block.id
        self.used[key] = self.used.get(key, 0) + 1
        out = render(model, camera, pose, backend=self.backend)
        rgb = np.clip(np.rint(out["color"] * 255.0), 0, 255).astype(np.uint8)
        depth = np.where(out["alpha"] >= self.min_alpha, out["depth"], 0.0).astype(np.float32)
        return rgb, depth
