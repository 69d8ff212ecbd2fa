"""3DGS training: data loading, the trainer (checkpoints, resume, evaluation) and `main`.

    from services.splat import confs, main
    main(confs["fast"], "scene/gt/sparse", "scene/images", "runs/splat", prefix="aerial/")

Writes OUT/point_cloud.ply (3DGS PLY), OUT/metrics.json (PSNR / SSIM / L1 on the held-out views: every
`test_every`-th image by name, as in 3DGS), OUT/views.json (the cameras it trained on), OUT/conf.json and
OUT/ckpts/step_NNNNNN.pt (parameters, optimizer moments, strategy state, step and RNG states: a killed run
resumes from the latest one and ends with the same parameters as an uninterrupted run).
"""

from __future__ import annotations

import json
import logging
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
import torch

from services.colmap_model import Camera, Pose
from services.conf import merge_conf
from services.geometry import scaled_intrinsics
from shared.logging import stage

from .backend import rasterization, resolve_backend
from .loss import photometric_loss, psnr, sample_depth, sparse_depth_loss, ssim, ssim_stats
from .model import activated, create_splats, random_points, splats_from_tensors
from .ply import save_ply
from .projection import viewmat_from_pose
from .render import latest_checkpoint
from .strategy import DefaultStrategy

log = logging.getLogger("midview.splat")

_DEFAULT: dict[str, Any] = {
    "steps": 30_000,
    "max_width": 1500,  # images are downsampled to at most this width
    "sh_degree": 3,
    "sh_degree_interval": 1000,  # one more SH degree every this many steps
    "init_opacity": 0.1,
    "init_scale": 1.0,
    "init_random": 0,  # random Gaussians added in the cameras' bounding box (all of them without points)
    "ssim_lambda": 0.2,
    # weight of the sparse-depth loss (loss.sparse_depth_loss against the SfM points each view sees;
    # gsplat's simple_trainer uses 1e-2; 0: off). On `small` (CPU, 1500 steps at 400 px) 0.1 took the
    # median depth error at the held-out views' SfM points from 3.8% to 0.8% and in the low views from 9.9%
    # to 4.7%, midview's GT-correct matches from 593 to 637 and their pooled precision from 0.935 to 0.949
    # (0.5: 0.3%, 3.7%, 649 at 0.918); held-out PSNR within 0.2 dB
    "depth_lambda": 0.1,
    "lr": {
        "means": 1.6e-4,  # times the scene extent, decays exponentially to means_final
        "means_final": 1.6e-6,
        "scales": 5e-3,
        "quats": 1e-3,
        "opacities": 5e-2,
        "sh0": 2.5e-3,
        "shN": 2.5e-3 / 20,
    },
    "strategy": asdict(DefaultStrategy()),
    "background": [0.0, 0.0, 0.0],
    "test_every": 8,  # every 8th image (by name) is held out; 0: none
    "ckpt_every": 1000,
    "keep_ckpts": 2,
    "seed": 0,
    "torch_threads": 1,  # for the CPU backend; numba runs the rasterizer on all cores
    "save_test_renders": True,
    "log_every": 100,  # log mean loss / PSNR every this many steps when there is no progress bar
    # seconds of training at most (None: unbounded): every `budget_every` steps the run's length is set
    # to what the rest of the budget allows at the pace of the last ones (at most `steps`); the means'
    # learning rate decays over that length. Time-based, so not reproducible step for step
    "time_budget_s": None,
    "budget_every": 50,
    # passes over the training images at most (None: unbounded): a small block trains fewer than `steps`
    # steps, its schedule scaled with them (epochs_capped)
    "max_epochs": None,
    # coarse to fine: the first `coarse_until` of the run's steps (a fraction of its length) render the
    # images at `coarse_scale` of their size (0: off). Cheaper steps place and densify the Gaussians, the
    # rest fit the detail at full size
    "coarse_until": 0.0,
    "coarse_scale": 0.5,
}


confs: dict[str, dict[str, Any]] = {
    # the 3DGS paper's recipe
    "default": merge_conf(_DEFAULT, {"name": "default"}),
    # ~10 minutes on 2 CPU cores for a 40-image aerial block (26.6 dB held-out PSNR on the synthetic
    # `small` preset): 2000 steps at 320 px, densification until step 1000, at most 60k Gaussians
    "fast": merge_conf(
        _DEFAULT,
        {
            "name": "fast",
            "steps": 2000,
            "max_width": 320,
            "sh_degree": 1,
            "sh_degree_interval": 500,
            "ckpt_every": 500,
            "strategy": {
                "refine_start_iter": 200,
                "refine_stop_iter": 1000,
                "refine_every": 100,
                "reset_every": 3000,
                "max_gaussians": 60_000,
            },
        },
    ),
}


# step-based entries of a conf that `rescale_schedule` scales (dotted keys; 0 means "off" and stays 0)
SCHEDULE_KEYS: dict[str, int] = {  # key -> smallest value once scaled
    "sh_degree_interval": 1,
    "strategy.refine_start_iter": 1,
    "strategy.refine_stop_iter": 2,
    "strategy.reset_every": 1,
    "strategy.refine_scale2d_stop_iter": 1,
    "strategy.pause_refine_after_reset": 1,
}


def rescale_schedule(conf: dict, steps: int) -> dict:
    """`conf` (completed with the defaults) trained for `steps` steps, its step-based schedule
    (`SCHEDULE_KEYS`: SH degree interval, densification start / stop, opacity reset) scaled by
    steps / conf["steps"], up or down, so the run keeps the preset's proportions.

    Kept as they are: `strategy.refine_every` (how many views' gradients each densification averages; a
    1000-step run refining every 3 steps would decide on noise), `ckpt_every` and the learning rates (the
    means' decay already follows conf["steps"])."""
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    out = merge_conf(_DEFAULT, conf)
    f = steps / max(int(out["steps"]), 1)
    out["steps"] = steps
    if f == 1.0:
        return out
    for key, low in SCHEDULE_KEYS.items():
        *path, last = key.split(".")
        d = out
        for k in path:
            d = d[k]
        if d.get(last, 0) > 0:
            d[last] = max(low, int(d[last] * f))
    return out


def epochs_capped(conf: dict, n_images: int) -> dict:
    """`conf` trained for at most conf["max_epochs"] passes over `n_images` training images: its steps
    capped at max_epochs x n_images, its schedule (rescale_schedule) and checkpoints scaled with them;
    `conf` itself without max_epochs or where the cap is not below its steps."""
    c = merge_conf(_DEFAULT, conf)
    if not c["max_epochs"] or n_images < 1:
        return conf
    steps = max(1, int(round(float(c["max_epochs"]) * n_images)))
    if steps >= int(c["steps"]):
        return conf
    out = rescale_schedule(c, steps)
    out["ckpt_every"] = max(1, int(c["ckpt_every"]) * steps // int(c["steps"]))
    return out


def check_conf(conf: dict) -> dict:
    """`conf` if its entries are in range, else ValueError with the reason (the kinds are checked by
    `parse_overrides`)."""
    c = merge_conf(_DEFAULT, conf)
    if not 0.0 <= c["coarse_until"] <= 1.0:
        raise ValueError(f"coarse_until is a fraction of the run, 0 to 1 (0: off), got {c['coarse_until']}")
    if not 0.0 < c["coarse_scale"] <= 1.0:
        raise ValueError(f"coarse_scale must be in (0, 1], got {c['coarse_scale']}")
    if c["max_epochs"] is not None and not float(c["max_epochs"]) > 0:
        raise ValueError(f"max_epochs must be positive (None: unbounded), got {c['max_epochs']}")
    return conf


@dataclass
class View:
    """One training or test camera; image (H, W, 3) float in [0, 1] at (width, height)."""

    name: str
    K: torch.Tensor
    viewmat: torch.Tensor
    width: int
    height: int
    image: torch.Tensor | None = None
    depth_pixels: torch.Tensor | None = None  # (M, 2) where the SfM points this image sees project
    depth_targets: torch.Tensor | None = None  # (M,) their z-depth in this camera
    limits: tuple[float, ...] | None = None  # a crop's: the projection bounds of its full image


@dataclass
class SceneData:
    views: list[View]
    points: np.ndarray  # (P, 3) initial points
    colors: np.ndarray  # (P, 3) in [0, 1]
    train_ids: list[int] = field(default_factory=list)
    test_ids: list[int] = field(default_factory=list)

    @classmethod
    def from_views(cls, views: list[View], points: np.ndarray, colors: np.ndarray, test_every: int = 8):
        views = sorted(views, key=lambda v: v.name)
        test = [i for i in range(len(views)) if test_every > 0 and i % test_every == 0 and len(views) > 1]
        train = [i for i in range(len(views)) if i not in test]
        return cls(views, np.asarray(points, float), np.asarray(colors, float), train, test)


def scaled_view(v: View, scale: float) -> View:
    """`v` with its camera, image and sparse-depth pixels at `scale` of its size (area-averaged image)."""
    w, h = max(1, int(round(v.width * scale))), max(1, int(round(v.height * scale)))
    sx, sy = w / v.width, h / v.height
    K = torch.diag(torch.tensor([sx, sy, 1.0], dtype=v.K.dtype)) @ v.K
    image = None
    if v.image is not None:
        img = torch.nn.functional.interpolate(v.image.permute(2, 0, 1)[None], size=(h, w), mode="area")
        image = img[0].permute(1, 2, 0).contiguous()
    pix = None if v.depth_pixels is None else v.depth_pixels * torch.tensor([sx, sy])
    return View(v.name, K, v.viewmat, w, h, image, pix, v.depth_targets, v.limits)


def load_image(path: Path, width: int, height: int) -> torch.Tensor:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"cannot read image {path}")
    if (img.shape[1], img.shape[0]) != (width, height):
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)).float() / 255.0


def load_scene(
    sparse: str | Path,
    images: str | Path | None,
    max_width: int | None = 1500,
    prefix: str = "",
    test_every: int = 8,
) -> SceneData:
    """Cameras, poses and points of a COLMAP model (images whose names start with `prefix`), with their
    images from the folder `images` (None: no images, e.g. to render)."""
    rec = pycolmap.Reconstruction(str(sparse))
    views = []
    for img in rec.images.values():
        if not img.has_pose or not img.name.startswith(prefix):
            continue
        c = Camera.from_pycolmap(img.camera)
        K, w, h = scaled_intrinsics(c.K, c.width, c.height, max_width)
        pose = Pose.of_image(img)
        v = View(img.name, torch.tensor(K, dtype=torch.float32), viewmat_from_pose(pose.R, pose.t), w, h)
        ids = [p.point3D_id for p in img.points2D if p.has_point3D()]
        xyz = np.array([rec.points3D[i].xyz for i in ids], float).reshape(-1, 3)
        v.depth_pixels, v.depth_targets = sparse_depth(xyz, K, pose, w, h)
        if images is not None:
            v.image = load_image(Path(images) / img.name, w, h)
        views.append(v)
    if not views:
        raise ValueError(f"{sparse}: no registered images named {prefix}*")
    pts = [p.xyz for p in rec.points3D.values()]
    cols = [p.color / 255.0 for p in rec.points3D.values()]
    points = np.array(pts, float).reshape(-1, 3)
    colors = np.array(cols, float).reshape(-1, 3)
    return SceneData.from_views(views, points, colors, test_every)


MIN_DEPTH_FRACTION = 1e-3  # sparse-depth targets nearer than this fraction of a view's median are dropped


def sparse_depth(
    xyz: np.ndarray, K: np.ndarray, cam_from_world: Pose | np.ndarray, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels (M, 2) and z-depths (M,) of the points `xyz` (N, 3) in front of the camera and inside the
    image (float32 tensors). Points nearer than MIN_DEPTH_FRACTION of the median depth are left out: a
    degenerate SfM point at a camera's centre (seen in `midview demo`'s model: z = 1e-8 m where the median
    was 75 m) would make the loss in disparity 1e8 and pull the depth there towards zero."""
    pose = cam_from_world
    if not isinstance(pose, Pose):  # its (3, 4) matrix
        pose = Pose(np.asarray(pose)[:, :3], np.asarray(pose)[:, 3])
    uv, z = pose.project(np.asarray(K, float), xyz)
    keep = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    if keep.any():
        keep &= z > MIN_DEPTH_FRACTION * np.median(z[keep])
    return torch.tensor(uv[keep], dtype=torch.float32), torch.tensor(z[keep], dtype=torch.float32)


def camera_centers(views: list[View]) -> np.ndarray:
    return np.stack([(-v.viewmat[:3, :3].T @ v.viewmat[:3, 3]).numpy() for v in views])


def scene_extent(views: list[View]) -> float:
    """3DGS's `cameras_extent`: 1.1 x the largest distance of a camera centre from their mean."""
    c = camera_centers(views)
    r = float(np.linalg.norm(c - c.mean(0), axis=1).max()) * 1.1
    return r if r > 0 else 1.0


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(s: dict) -> None:
    torch.set_rng_state(s["torch"])
    np.random.set_state(s["numpy"])
    random.setstate(s["python"])


class Trainer:
    """Optimises Gaussians on `data` with the 3DGS recipe (see `confs`), saving into `out`.

    `init` (model.py layout): start from these Gaussians instead of the SfM points (a block's share of
    the whole-scene model). `frozen` (model.py layout): Gaussians rendered with the trained ones in every
    step but never optimised nor densified (the rest of the scene around a block)."""

    def __init__(
        self,
        conf: dict,
        data: SceneData,
        out: str | Path,
        backend: str = "auto",
        init: dict[str, torch.Tensor] | None = None,
        frozen: dict[str, torch.Tensor] | None = None,
    ):
        self.conf = check_conf(merge_conf(_DEFAULT, conf))
        self.data = data
        self.init = init
        self.out = Path(out)
        self.backend = resolve_backend(backend)
        self.device = torch.device("cuda" if self.backend == "cuda" else "cpu")
        self.extent = scene_extent([data.views[i] for i in data.train_ids] or data.views)
        self.strategy = DefaultStrategy(**self.conf["strategy"])
        self.splats: torch.nn.ParameterDict | None = None
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.strategy_state: dict = {}
        self.step = 0  # steps done
        self.total_steps = int(self.conf["steps"])  # the run's length: conf["steps"], or less (time budget)
        self._budget_told = self.total_steps  # the length last logged at INFO
        self._fine = False  # past the coarse phase (conf["coarse_until"])
        self.elapsed_s = 0.0  # training time so far, over resumes (checkpoints keep it)
        self.history: list[dict] = []
        self.frozen = None
        if frozen is not None and len(frozen["means"]):
            self.frozen = {k: v.detach().to(self.device) for k, v in activated(frozen).items()}

    # ---- model and optimizers
    def init_model(self) -> None:
        c = self.conf
        torch.manual_seed(c["seed"])
        if self.init is not None:
            self._set_model(splats_from_tensors(self.init).to(self.device))
            self.strategy_state = self.strategy.initialize_state(self.extent)
            return
        pts, cols = self.data.points, self.data.colors
        if c["init_random"] > 0 or len(pts) == 0:
            centers = camera_centers(self.data.views)
            lo = np.minimum(centers.min(0), pts.min(0) if len(pts) else centers.min(0))
            hi = np.maximum(centers.max(0), pts.max(0) if len(pts) else centers.max(0))
            rp, rc = random_points(max(c["init_random"], 1000 if len(pts) == 0 else 0), lo, hi, c["seed"])
            pts, cols = np.concatenate([pts, rp]), np.concatenate([cols, rc])
        splats = create_splats(pts, cols, c["sh_degree"], c["init_opacity"], c["init_scale"])
        self._set_model(splats.to(self.device))
        self.strategy_state = self.strategy.initialize_state(self.extent)

    def _set_model(self, splats: torch.nn.ParameterDict) -> None:
        self.splats = splats
        lr = self.conf["lr"]
        self.optimizers = {
            k: torch.optim.Adam(
                [{"params": [splats[k]], "lr": lr[k] * (self.extent if k == "means" else 1.0), "name": k}],
                eps=1e-15,
            )
            for k in splats.keys()
        }

    def means_lr(self, step: int) -> float:
        lr = self.conf["lr"]
        t = min(step / max(self.total_steps, 1), 1.0)
        return self.extent * lr["means"] * (lr["means_final"] / lr["means"]) ** t

    def sh_degree_at(self, step: int) -> int:
        """SH degree of a step: one more every conf["sh_degree_interval"] steps (0: all from the start)."""
        if not self.conf["sh_degree_interval"]:
            return self.conf["sh_degree"]
        return min(step // self.conf["sh_degree_interval"], self.conf["sh_degree"])

    def is_coarse(self, step: int) -> bool:
        """Whether `step` renders at conf["coarse_scale"]: the first conf["coarse_until"] of the run (its
        length as the time budget sets it; once a step is fine the rest are)."""
        c = self.conf
        if self._fine or c["coarse_scale"] == 1 or step >= c["coarse_until"] * self.total_steps:
            self._fine = True
        return not self._fine

    def view_at(self, step: int) -> int:
        """Training view of a step: a seeded permutation per epoch (stateless, so resumes see the same)."""
        ids = self.data.train_ids
        epoch, i = divmod(step, len(ids))
        perm = np.random.default_rng([self.conf["seed"], epoch]).permutation(len(ids))
        return ids[perm[i]]

    # ---- checkpoints
    def save_checkpoint(self) -> Path:
        d = self.out / "ckpts"
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"step_{self.step:06d}.pt"
        state = {
            "step": self.step,
            "splats": {k: v.detach().cpu() for k, v in self.splats.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "strategy_state": self.strategy_state,
            "rng": _rng_state(),
            "history": self.history,
            "conf": self.conf,
            "total_steps": self.total_steps,
            "elapsed_s": self.elapsed_s,
        }
        tmp = path.with_suffix(".tmp")
        torch.save(state, tmp)
        tmp.replace(path)
        for old in sorted(d.glob("step_*.pt"))[: -max(self.conf["keep_ckpts"], 1)]:
            old.unlink()
        return path

    def load_checkpoint(self, path: str | Path) -> None:
        ck = torch.load(path, map_location="cpu", weights_only=False)
        self._set_model(splats_from_tensors(ck["splats"]).to(self.device))
        for k, o in self.optimizers.items():
            o.load_state_dict(ck["optimizers"][k])
        self.strategy_state = {
            k: (v.to(self.device) if torch.is_tensor(v) else v) for k, v in ck["strategy_state"].items()
        }
        _set_rng_state(ck["rng"])
        self.step = int(ck["step"])
        self.history = list(ck.get("history", []))
        self.total_steps = int(ck.get("total_steps", self.conf["steps"]))
        self.elapsed_s = float(ck.get("elapsed_s", 0.0))

    # ---- rendering
    def render_view(
        self, v: View, sh_degree: int | None = None, depth: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """colors (H, W, 3), or (H, W, 4) with the expected depth last when `depth`; alphas; info."""
        p = activated(self.splats)
        if self.frozen is not None:
            p = {k: torch.cat([v, self.frozen[k]]) for k, v in p.items()}
        bg = torch.tensor(self.conf["background"] + [0.0] * depth, dtype=torch.float32, device=self.device)
        return rasterization(
            p["means"],
            p["quats"],
            p["scales"],
            p["opacities"],
            p["sh"],
            v.viewmat.to(self.device),
            v.K.to(self.device),
            v.width,
            v.height,
            sh_degree=self.conf["sh_degree"] if sh_degree is None else sh_degree,
            backgrounds=bg,
            render_mode="RGB+ED" if depth else "RGB",
            backend=self.backend,
            limits=v.limits,
        )

    # ---- training
    def train(self, resume: bool = False, stop_after: int | None = None, progress: bool = True) -> dict:
        """Train up to conf["steps"], or fewer within conf["time_budget_s"] (or stop once `stop_after`
        steps are done, as if killed)."""
        c = self.conf
        n_threads = torch.get_num_threads()
        if self.backend == "cpu" and c["torch_threads"]:
            torch.set_num_threads(int(c["torch_threads"]))
        try:
            ckpt = latest_checkpoint(self.out) if resume else None
            if ckpt is not None:
                self.load_checkpoint(ckpt)
                log.info("resumed from %s (step %d)", ckpt, self.step)
            else:
                self.init_model()
                if resume:
                    log.info("no checkpoint in %s: starting afresh", self.out)
            self._loop(stop_after, progress)
        finally:
            torch.set_num_threads(n_threads)
        return {"step": self.step, "num_gaussians": self.num_gaussians}

    @property
    def num_gaussians(self) -> int:
        """Gaussians of the model (0 before it is initialised)."""
        return 0 if self.splats is None else len(self.splats["means"])

    def _loop(self, stop_after: int | None, progress: bool) -> None:
        c = self.conf
        imgs: dict[str, torch.Tensor] = {}
        stats: dict[str, torch.Tensor] = {}
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=self.total_steps, initial=self.step, desc="splat", dynamic_ncols=True)
        t0 = time.perf_counter()
        elapsed0, pace = self.elapsed_s, None  # the pace is measured from the first check on (after JIT)
        coarse: dict[str, View] = {}
        while self.step < self.total_steps:
            step = self.step
            v = self.data.views[self.view_at(step)]
            if self.is_coarse(step):
                if v.name not in coarse:
                    coarse[v.name] = scaled_view(v, float(c["coarse_scale"]))
                v = coarse[v.name]
            elif coarse:  # the fine phase from here on: its pace is not the coarse one
                coarse, imgs, stats = {}, {}, {}
                log.info("step %d: coarse phase done, training at full size", step)
                if pace:
                    pace = (time.perf_counter(), step)
            if v.name not in imgs:
                imgs[v.name] = v.image.to(self.device)
                if self.device.type == "cpu":  # the target's half of SSIM, once per image (GPUs recompute)
                    with torch.no_grad():
                        stats[v.name] = ssim_stats(imgs[v.name])
            loss, colors, changed = self._train_step(v, step, imgs[v.name], stats.get(v.name))
            self.step = step + 1
            rec = {
                "step": self.step,
                "loss": float(loss.detach()),
                "psnr": psnr(colors.detach(), imgs[v.name]),
            }
            self.history.append(rec)
            self._report_step(rec, changed, bar, t0)
            self.elapsed_s = elapsed0 + time.perf_counter() - t0
            if c["time_budget_s"] and self.step % c["budget_every"] == 0:
                pace = self._fit_time_budget(pace) if pace else (time.perf_counter(), self.step)
                if bar is not None:
                    bar.total = self.total_steps
            if self.step % c["ckpt_every"] == 0 or self.step == self.total_steps:
                self.save_checkpoint()
            if stop_after is not None and self.step >= stop_after:
                break
        if bar is not None:
            bar.close()
        self.train_seconds = time.perf_counter() - t0

    def _train_step(
        self, v: View, step: int, target: torch.Tensor, target_stats: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, Any]:
        """One optimisation step on view v: render, photometric (and sparse depth) loss, backward, the
        optimisers' and the strategy's steps. (loss, rendered colours, what the strategy changed)."""
        c = self.conf
        self.optimizers["means"].param_groups[0]["lr"] = self.means_lr(step)
        use_depth = c["depth_lambda"] > 0 and v.depth_targets is not None and len(v.depth_targets) > 0
        colors, _, info = self.render_view(v, self.sh_degree_at(step), depth=use_depth)
        self.strategy.step_pre_backward(self.splats, self.optimizers, self.strategy_state, step, info)
        if use_depth:
            colors, depth = colors[..., :3], colors[..., 3]
        loss, terms = photometric_loss(colors, target, c["ssim_lambda"], target_stats)
        if use_depth:
            dl = sparse_depth_loss(
                depth, v.depth_pixels.to(self.device), v.depth_targets.to(self.device), self.extent
            )
            loss = loss + c["depth_lambda"] * dl
        loss.backward()
        for o in self.optimizers.values():
            o.step()
            o.zero_grad(set_to_none=True)
        changed = self.strategy.step_post_backward(
            self.splats, self.optimizers, self.strategy_state, step, self._own(info)
        )
        return loss, colors, changed

    def _report_step(self, rec: dict, changed: Any, bar: Any, t0: float) -> None:
        """The strategy's changes, every log_every steps the mean loss and PSNR, or the progress bar."""
        c = self.conf
        if changed and self.strategy.verbose:
            log.info("step %d: %s, %d Gaussians", self.step, changed, len(self.splats["means"]))
        if bar is None and c["log_every"] and self.step % c["log_every"] == 0:
            last = self.history[-c["log_every"] :]
            log.info(
                "step %d: loss %.4f, PSNR %.2f dB (mean of the last %d), %d Gaussians, %.0f s",
                self.step,
                np.mean([r["loss"] for r in last]),
                np.mean([r["psnr"] for r in last]),
                len(last),
                len(self.splats["means"]),
                time.perf_counter() - t0,
            )
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr']:.2f}", n=len(self.splats["means"]))

    def _own(self, info: dict) -> dict:
        """`info` of a render trimmed to the trained Gaussians (the frozen ones come after them)."""
        if self.frozen is None:
            return info
        n = len(self.splats["means"])
        m2 = info["means2d"]
        own = m2.detach()[:n].clone()
        if m2.requires_grad and m2.retains_grad and m2.grad is not None:
            own.grad = m2.grad[:n]
        return {**info, "means2d": own, "radii": info["radii"][:n], "depths": info["depths"][:n]}

    def _fit_time_budget(self, pace: tuple[float, int]) -> tuple[float, int]:
        """Set total_steps to what the rest of conf["time_budget_s"] allows at the pace since `pace`
        (time, step), at most conf["steps"]; returns the new reference (now, step)."""
        now = time.perf_counter()
        per_step = (now - pace[0]) / max(self.step - pace[1], 1)
        left = float(self.conf["time_budget_s"]) - self.elapsed_s
        fits = min(self.step + max(int(left / max(per_step, 1e-9)), 0), int(self.conf["steps"]))
        if fits != self.total_steps:
            # the pace wavers by a few percent: INFO only when the length moves 5% from the last one told
            told = self._budget_told
            level = logging.INFO if abs(fits - told) >= 0.05 * told else logging.DEBUG
            if level == logging.INFO:
                self._budget_told = fits
            log.log(
                level,
                "time budget %.0f s: %d steps instead of %d (%.0f s spent, %.3f s per step)",
                self.conf["time_budget_s"],
                fits,
                self.total_steps,
                self.elapsed_s,
                per_step,
            )
            self.total_steps = fits
        return now, self.step

    # ---- evaluation and export
    @torch.no_grad()
    def evaluate(self, ids: list[int] | None = None, save_dir: Path | None = None) -> dict:
        """PSNR / SSIM / L1 of the views `ids` (default: the held-out ones), and the median relative error
        of the rendered depth at the SfM points each view sees (depth_err; NaN without points)."""
        ids = self.data.test_ids if ids is None else ids
        per = {}
        for i in ids:
            v = self.data.views[i]
            out, _, _ = self.render_view(v, depth=True)
            out, depth = out[..., :3].clamp(0, 1).cpu(), out[..., 3].cpu()
            gt = v.image
            per[v.name] = {
                "psnr": psnr(out, gt),
                "ssim": float(ssim(out, gt)),
                "l1": float((out - gt).abs().mean()),
                "depth_err": depth_error(depth, v),
            }
            if save_dir is not None:
                save_dir.mkdir(parents=True, exist_ok=True)
                pair = (torch.cat([gt, out], 1).numpy() * 255).round().astype(np.uint8)
                cv2.imwrite(str(save_dir / (v.name.replace("/", "__") + ".png")), pair[..., ::-1])
        mean = {
            k: float(np.mean([p[k] for p in per.values()])) if per else float("nan")
            for k in ("psnr", "ssim", "l1")
        }
        errs = [p["depth_err"] for p in per.values() if np.isfinite(p["depth_err"])]
        mean["depth_err"] = float(np.median(errs)) if errs else float("nan")
        return {**mean, "n_views": len(per), "views": per}

    def export(self) -> Path:
        return save_ply(self.splats, self.out / "point_cloud.ply")


def depth_error(depth: torch.Tensor, v: View) -> float:
    """Median |rendered - SfM| / SfM depth at the SfM points of view `v` (NaN when it has none)."""
    if v.depth_targets is None or len(v.depth_targets) == 0:
        return float("nan")
    d = sample_depth(depth, v.depth_pixels)
    return float(((d - v.depth_targets).abs() / v.depth_targets).median())


def write_views(views: list[View], path: Path) -> Path:
    """The cameras as JSON: name, width, height, K, cam_from_world R and t."""
    rows = [
        {
            "name": v.name,
            "width": v.width,
            "height": v.height,
            "K": v.K.tolist(),
            "R": v.viewmat[:3, :3].tolist(),
            "t": v.viewmat[:3, 3].tolist(),
        }
        for v in views
    ]
    path.write_text(json.dumps(rows, indent=1))
    return path


def main(
    conf: dict,
    sparse: str | Path,
    images: str | Path,
    out: str | Path,
    backend: str = "auto",
    resume: bool = False,
    prefix: str = "",
    progress: bool = True,
) -> Path:
    """Train a 3DGS model of the images of COLMAP model `sparse` (names starting with `prefix`) found in
    `images`; returns `out` (see the module docstring for its files)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    conf = merge_conf(_DEFAULT, conf)
    with stage("splat", log):
        t0 = time.perf_counter()
        data = load_scene(sparse, images, conf["max_width"], prefix, conf["test_every"])
        log.info(
            "%d views (%d held out) at %dx%d, %d points",
            len(data.views),
            len(data.test_ids),
            data.views[0].width,
            data.views[0].height,
            len(data.points),
        )
        trainer = Trainer(epochs_capped(conf, len(data.train_ids)), data, out, backend)
        (out / "conf.json").write_text(json.dumps(trainer.conf, indent=1))
        write_views(data.views, out / "views.json")
        t_load = time.perf_counter() - t0
        trainer.train(resume=resume, progress=progress)
        trainer.export()
        t1 = time.perf_counter()
        save_dir = out / "renders" / "test" if conf["save_test_renders"] else None
        test = trainer.evaluate(save_dir=save_dir)
        train_eval = trainer.evaluate(trainer.data.train_ids[:: max(1, len(trainer.data.train_ids) // 8)])
        metrics = {
            "steps": trainer.step,
            "num_gaussians": trainer.num_gaussians,
            "backend": trainer.backend,
            "resolution": [data.views[0].width, data.views[0].height],
            "n_train": len(data.train_ids),
            "n_test": len(data.test_ids),
            "seconds": {
                "load": t_load,
                "train": getattr(trainer, "train_seconds", float("nan")),
                "eval": time.perf_counter() - t1,
            },
            "test": test,
            "train_subset": {k: train_eval[k] for k in ("psnr", "ssim", "l1", "depth_err", "n_views")},
        }
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
        log.info(
            "test PSNR %.2f dB, SSIM %.3f, depth error %.1f%% (median, at the SfM points) on %d views; "
            "%d Gaussians",
            test["psnr"],
            test["ssim"],
            100 * test["depth_err"],
            test["n_views"],
            metrics["num_gaussians"],
        )
    return out
