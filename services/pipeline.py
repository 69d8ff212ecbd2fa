"""The pipeline stages over a job folder, and an in-process runner (`midview run`, and the Celery workers
stage by stage).

A job folder holds everything of one job:

```
JOB/job.json             inputs (aerial/ground image folders, POS, cameras), JobOptions, settings
JOB/images/{aerial,ground}  links to the input image folders (image names: aerial/X.jpg, ground/Y.jpg)
JOB/cameras.json         intrinsics per set (the given cameras.json; else the aerial model's / EXIF)
JOB/sfm/                 aerial_sfm:   sparse/, georef.json, database.db, report.json
JOB/splat/               train_splat:  point_cloud.ply, metrics.json, ckpts/
JOB/plan/views.json      plan_views
JOB/blocks/              train_blocks: plan.json, BLOCK/point_cloud.ply + block.json (+ ckpts/), report.json
JOB/views/               render_views: NAME.png, NAME.depth.npy, views.json
JOB/features/            match_views:  the aerial and ground images' matching features (cache)
JOB/matches/NAME.h5      match_views:  one file per view
JOB/transfer/            reduce:       matches.h5, database.db, ground_poses.json, report.json
JOB/combined/            combined_sfm: sparse/, database.db, report.json
JOB/splat_all/           splat_all:    the 3DGS of all registered images (optional stage), like splat/
JOB/stages/STAGE.json    done markers: input fingerprint, outputs, seconds, summary
```

Every stage is a function of the job folder. A stage whose outputs exist and whose input fingerprint
(a hash of its conf and of its input files' names, sizes and contents) matches its marker is
skipped, so a rerun skips finished stages and resumes a failed one (3DGS training resumes from its last
checkpoint, view matching skips views already matched). Stages made of independent units (`FanOut`:
the blocks of train_blocks, the views of match_views) run them one by one here and one task each in the
service. Progress goes through a callback
`progress(stage, fraction, message)`.

    job = Job.create("runs/job1", aerial="data/aerial", ground="data/ground", pos="data/pos.csv")
    run(job, progress=print)
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.conf import merge_conf
from shared.job_options import FANOUT_STAGES, OPTIONAL_STAGES, STAGE_QUEUES, STAGES, JobOptions

logger = logging.getLogger("midview.pipeline")

Progress = Callable[[str, float, str], None]
JOB_FILE = "job.json"

# pipeline knobs that JobOptions does not carry (job.json "settings"), with their defaults
DEFAULT_SETTINGS: dict[str, Any] = {
    "renderer": "splat",  # "splat" (the product) or "gt" (ground truth of a synthetic scene: bench only)
    "scene": None,  # synthetic scene folder, for renderer "gt"
    "splat_backend": "auto",
    "torch_threads": None,  # None: leave torch's setting; 1 is much faster on a loaded 2-core machine
    "sfm": {},  # overrides of services.sfm confs
    "splat": {},  # overrides of services.splat confs
    "blocks": {},  # overrides of services.splat.blocks confs["default"]
    "viewpoints": {},  # overrides of services.views confs (the planners)
    "views": {},  # services.views.rendering conf
    "matching": {},  # overrides of services.matching.views confs (e.g. resize_max)
    "transfer": {},  # overrides of services.reduce.default_conf
    "combined": {},  # overrides of services.sfm.combined.default_conf
}


def parse_settings_overrides(
    splat: list[str], viewpoints: list[str], matching: list[str], matcher: str = "aliked-lightglue"
) -> dict[str, dict]:
    """`KEY=VALUE` strings of the 3DGS, viewpoint and matching (the matcher's) confs -> the job settings
    that override them (services.conf.parse_overrides: ValueError with the reason)."""
    from services.conf import parse_overrides
    from services.matching.views import confs as match_confs
    from services.splat import confs as splat_confs
    from services.splat.train import check_conf
    from services.views import confs as view_confs

    splat_over = parse_overrides(splat, splat_confs["fast"])
    check_conf(merge_conf(splat_confs["fast"], splat_over))
    return {
        "splat": splat_over,
        "viewpoints": parse_overrides(viewpoints, view_confs["both"]),
        "matching": parse_overrides(matching, match_confs.get(matcher, match_confs["aliked-lightglue"])),
    }


# -- job folder ----------------------------------------------------------------------------------
class _File:
    """A named file (or folder) of a stage's folder: `job.sfm.sparse` is JOB/sfm/sparse."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __get__(self, folder: Folder | None, owner: type | None = None) -> Any:
        return self if folder is None else folder.dir / self.name


class Folder:
    """A stage's folder of a job (`dir`) and, in subclasses, its named files."""

    def __init__(self, path: Path) -> None:
        self.dir = path

    def __truediv__(self, name: str) -> Path:
        return self.dir / name

    def glob(self, pattern: str) -> list[Path]:
        return sorted(self.dir.glob(pattern))


class SfmFolder(Folder):
    sparse = _File("sparse")
    georef = _File("georef.json")
    database = _File("database.db")
    report = _File("report.json")


class SplatFolder(Folder):
    model = _File("point_cloud.ply")
    metrics = _File("metrics.json")
    skipped = _File("skipped.json")


class PlanFolder(Folder):
    views = _File("views.json")


class BlocksFolder(Folder):
    plan = _File("plan.json")
    report = _File("report.json")


class ViewsFolder(Folder):
    doc = _File("views.json")


class TransferFolder(Folder):
    matches = _File("matches.h5")
    ground_poses = _File("ground_poses.json")
    database = _File("database.db")
    report = _File("report.json")


class CombinedFolder(Folder):
    sparse = _File("sparse")
    georef = _File("georef.json")
    report = _File("report.json")


class Job:
    """A job folder: inputs, options, settings and the paths of every stage's files."""

    def __init__(self, root: str | Path, inputs: dict, options: JobOptions, settings: dict):
        self.root = Path(root)
        self.inputs = dict(inputs)
        self.options = options
        self.settings = merge_conf(DEFAULT_SETTINGS, settings)

    # construction
    @classmethod
    def create(
        cls,
        root: str | Path,
        aerial: str | Path,
        ground: str | Path,
        pos: str | Path,
        cameras: str | Path | None = None,
        options: JobOptions | dict | None = None,
        settings: dict | None = None,
    ) -> Job:
        """Write job.json and the image links; an existing job folder keeps its stage outputs. Bad options
        or missing inputs raise before anything is written."""
        root = Path(root)
        opts = options if isinstance(options, JobOptions) else JobOptions.model_validate(options or {})
        inputs = {
            "aerial": str(Path(aerial).resolve()),
            "ground": str(Path(ground).resolve()),
            "pos": str(Path(pos).resolve()),
            "cameras": str(Path(cameras).resolve()) if cameras else None,
        }
        for k in ("aerial", "ground"):
            if not Path(inputs[k]).is_dir():
                raise FileNotFoundError(f"{k} image folder {inputs[k]} does not exist")
        if not Path(inputs["pos"]).is_file():
            raise FileNotFoundError(f"POS file {inputs['pos']} does not exist")
        if inputs["cameras"] and not Path(inputs["cameras"]).is_file():
            raise FileNotFoundError(f"cameras file {inputs['cameras']} does not exist")
        settings = dict(settings or {})
        if settings.get("scene"):
            settings["scene"] = str(Path(settings["scene"]).resolve())
        root.mkdir(parents=True, exist_ok=True)
        job = cls(root, inputs, opts, settings)
        job.save()
        job.link_images()
        return job

    @classmethod
    def load(cls, root: str | Path) -> Job:
        root = Path(root)
        doc = json.loads((root / JOB_FILE).read_text())
        return cls(root, doc["inputs"], JobOptions.model_validate(doc["options"]), doc.get("settings", {}))

    def save(self) -> Path:
        doc = {
            "inputs": self.inputs,
            "options": self.options.model_dump(mode="json"),
            "settings": self.settings,
        }
        path = self.root / JOB_FILE
        path.write_text(json.dumps(doc, indent=1))
        return path

    def link_images(self) -> None:
        for s in ("aerial", "ground"):
            link = self.image_dir / s
            link.parent.mkdir(parents=True, exist_ok=True)
            target = Path(self.inputs[s])
            if link.is_symlink() and Path(os.readlink(link)) == target:
                continue
            if link.is_symlink() or link.is_file():
                link.unlink()
            elif link.is_dir():
                shutil.rmtree(link)
            link.symlink_to(target, target_is_directory=True)

    # paths
    @property
    def image_dir(self) -> Path:
        return self.root / "images"

    @property
    def pos(self) -> Path:
        return Path(self.inputs["pos"])

    @property
    def cameras(self) -> Path:
        return self.root / "cameras.json"

    def dir(self, name: str) -> Path:
        return self.root / name

    @property
    def sfm(self) -> SfmFolder:
        return SfmFolder(self.dir("sfm"))

    @property
    def splat(self) -> SplatFolder:
        return SplatFolder(self.dir("splat"))

    @property
    def plan(self) -> PlanFolder:
        return PlanFolder(self.dir("plan"))

    @property
    def blocks(self) -> BlocksFolder:
        return BlocksFolder(self.dir("blocks"))

    @property
    def views(self) -> ViewsFolder:
        return ViewsFolder(self.dir("views"))

    @property
    def matches(self) -> Folder:
        return Folder(self.dir("matches"))

    @property
    def transfer(self) -> TransferFolder:
        return TransferFolder(self.dir("transfer"))

    @property
    def combined(self) -> CombinedFolder:
        return CombinedFolder(self.dir("combined"))

    @property
    def splat_all(self) -> SplatFolder:
        return SplatFolder(self.dir("splat_all"))

    @property
    def stages_dir(self) -> Path:
        return self.root / "stages"

    @property
    def features_path(self) -> Path:
        from services.matching.views import feature_conf

        return self.dir("features") / f"{feature_conf(self.match_conf())['output']}.h5"

    # confs derived from the options and settings
    def sfm_conf(self) -> dict:
        from services import sfm

        base = sfm.confs[self.options.sfm_features]
        over: dict[str, Any] = {"mapping": {"seed": self.options.seed}}
        if self.options.out_crs:
            over["export"] = {"out_crs": self.options.out_crs}
        return merge_conf(base, merge_conf(over, self.settings["sfm"]))

    def splat_conf(self) -> dict:
        from services.splat import confs, rescale_schedule, resolve_backend

        be = resolve_backend(self.settings["splat_backend"])
        steps = int(self.options.splat_steps)
        # the preset's schedule scaled to `steps` (as `midview splat train --steps` does)
        c = rescale_schedule(confs["default" if be == "cuda" else "fast"], steps)
        over: dict[str, Any] = {
            "max_width": int(self.options.splat_max_width),
            "seed": int(self.options.seed),
            "save_test_renders": False,
            "ckpt_every": max(1, steps // 10),
        }
        if self.options.splat_time_budget_s is not None:
            over["time_budget_s"] = float(self.options.splat_time_budget_s)
        return merge_conf(merge_conf(c, over), self.settings["splat"])

    def viewpoint_conf(self) -> dict:
        from services import views

        c = views.confs[self.options.view_planner]
        over = {"views_per_ground_image": int(self.options.views_per_ground_image), "seed": self.options.seed}
        return merge_conf(merge_conf(c, over), self.settings["viewpoints"])

    def match_conf(self) -> dict:
        from services.matching import views as mv

        c = mv.confs[self.options.matcher]
        return merge_conf(
            merge_conf(c, {"max_keypoints": int(self.options.max_keypoints)}), self.settings["matching"]
        )

    def transfer_conf(self) -> dict:
        from services import reduce

        return merge_conf(reduce.default_conf, self.settings["transfer"])

    def combined_conf(self) -> dict:
        from services.sfm import combined as combined_sfm

        conf = merge_conf(combined_sfm.default_conf, self.settings["combined"])
        if conf["pos_limits"] is None:  # the same POS limits as the reducer's poses
            conf["pos_limits"] = self.transfer_conf()["pnp"]
        return conf

    def blocks_conf(self) -> dict:
        """services.splat.blocks conf: the default, each block trained `block_steps` steps (its schedule
        scaled to them), then the settings' overrides."""
        from services.splat import rescale_schedule
        from services.splat.blocks import confs

        steps = max(1, int(self.options.block_steps))
        train = rescale_schedule(confs["default"]["train"], steps)
        train["ckpt_every"] = max(1, steps // 6)
        over = {"train": train, "block_px": int(self.options.block_px)}
        return merge_conf(merge_conf(confs["default"], over), self.settings["blocks"])

    @property
    def uses_blocks(self) -> bool:
        """Whether the views render from trained blocks (train_blocks among the job's stages, blocks
        trained at least one step, the 3DGS renderer)."""
        return (
            self.settings["renderer"] == "splat"
            and "train_blocks" in self.options.stages
            and self.options.block_steps > 0
        )

    # renderer
    def renderer(self, blocks: bool = True):
        """The views' renderer: the trained blocks over the whole-scene 3DGS when the job has them (and
        `blocks`), else the whole-scene 3DGS, or the ground truth (renderer "gt")."""
        from services import views

        if self.settings["renderer"] == "gt":
            if not self.settings.get("scene"):
                raise ValueError("renderer 'gt' needs settings.scene: a synthetic scene folder")
            return views.GroundTruthRenderer(self.settings["scene"], self.sfm.sparse)
        if self.settings["renderer"] != "splat":
            raise ValueError(f"unknown renderer {self.settings['renderer']!r} (splat, gt)")
        min_alpha = self.settings["views"].get("min_alpha", 0.5)
        if blocks and self.uses_blocks and (self.blocks.report).is_file():
            from services.views import BlockRenderer

            return BlockRenderer(self.splat.dir, self.blocks.dir, self.settings["splat_backend"], min_alpha)
        return views.SplatRenderer(self.splat.dir, self.settings["splat_backend"], min_alpha)

    def renderer_inputs(self, blocks: bool = True) -> list[Path]:
        if self.settings["renderer"] == "gt":
            return [Path(self.settings["scene"]) / "gt" / "scene.json"]
        own = [self.blocks.plan, self.blocks.report]
        return [self.splat.model, *(own if blocks and self.uses_blocks else [])]


# -- fingerprints and markers --------------------------------------------------------------------
_SKIP_SUFFIXES = (".tmp", "-wal", "-shm", "-journal")


def _files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if not path.is_dir():
        return []
    out = []
    for dirpath, dirnames, filenames in os.walk(path, followlinks=True):
        dirnames.sort()
        for f in sorted(filenames):
            if f.startswith(".") or f.endswith(_SKIP_SUFFIXES):
                continue
            out.append(Path(dirpath) / f)
    return out


DIGESTS_FILE = ".digests.json"  # the job folder's content digests, by file stat (services.digests)


def fingerprint(conf: Any, inputs: list[Path], root: Path | None = None) -> str:
    """sha256 of the conf (JSON) and of the inputs' file names, sizes and contents (sha256, cached by
    file stat in ROOT/.digests.json). Names under `root` (the job folder) are taken relative to it, so
    that a job folder can be moved, or its stage folders shared with another job through links; the
    same files give the same fingerprint on every machine, whenever they were written."""
    from services.digests import DigestCache

    def name(p: Path) -> str:
        if root is not None:
            try:
                return str(Path(os.path.abspath(p)).relative_to(os.path.abspath(root)))
            except ValueError:
                pass
        return str(p)

    h = hashlib.sha256()
    h.update(json.dumps(conf, sort_keys=True, default=str).encode())
    with DigestCache(Path(root) / DIGESTS_FILE if root is not None else None) as dc:
        for p in inputs:
            p = Path(p)
            h.update(f"#{name(p)}".encode())
            for f in _files(p):
                try:
                    size, sha = f.stat().st_size, dc.digest(f)
                except FileNotFoundError:
                    continue
                h.update(f"{name(f)}:{size}:{sha}\n".encode())
    return h.hexdigest()


@dataclass(frozen=True)
class FanOut:
    """A stage made of independent units of work (the service runs one task per unit, on `queue(job)`).

    prepare(job) -> files: done once before the units (every unit task gets its files); units(job) ->
    their names (after prepare); unit(job, name, report) -> the files one unit wrote (a unit already
    done returns at once); marker(name) -> the job-relative file whose presence tells a unit is done;
    finish(job, names) -> the stage's summary, once every unit is done."""

    prepare: Callable[[Job], list[Path]]
    units: Callable[[Job], list[str]]
    unit: Callable[[Job, str, Callable[[float, str], None]], list[Path]]
    marker: Callable[[str], str]
    queue: Callable[[Job], str]
    finish: Callable[[Job, list[str]], dict]
    ready: Callable[[Job], bool]


def run_fanout(stage: str) -> Callable[[Job, Callable[[float, str], None]], dict]:
    """The in-process run of a fan-out stage: prepare, every unit in order, finish."""

    def run(job: Job, report: Callable[[float, str], None]) -> dict:
        fan = REGISTRY[stage].fanout
        _set_threads(job)
        report(0.0, "preparing the units")
        fan.prepare(job)
        names = fan.units(job)
        for i, n in enumerate(names):
            fan.unit(job, n, lambda f, m, i=i: report((i + min(max(f, 0.0), 1.0)) / len(names), m))
            report((i + 1) / len(names), f"{n} done ({i + 1}/{len(names)})")
        return fan.finish(job, names)

    return run


@dataclass
class StageDef:
    """One stage: run(job, report) -> summary dict; its conf, inputs and outputs derived from the job;
    the folders of the job it owns (`dirs`, the first its own), the files it writes outside them
    (`extra`), and its user-facing outputs (`artifacts`: (path or folder/* or folder/*.ext relative to
    the job folder, kind)), which the workers sync, record and list from here."""

    name: str
    run: Callable[[Job, Callable[[float, str], None]], dict]
    conf: Callable[[Job], Any]
    inputs: Callable[[Job], list[Path]]
    outputs: Callable[[Job], list[Path]]
    dirs: tuple[str, ...] = ()
    extra: tuple[str, ...] = ()
    artifacts: tuple[tuple[str, str], ...] = ()
    fanout: FanOut | None = None

    @property
    def queue(self) -> str:
        return STAGE_QUEUES[self.name]


def marker_path(job: Job, stage: str) -> Path:
    return job.stages_dir / f"{stage}.json"


def read_marker(job: Job, stage: str) -> dict | None:
    try:
        return json.loads(marker_path(job, stage).read_text())
    except (FileNotFoundError, ValueError):
        return None


def is_done(job: Job, stage: str) -> bool:
    """Whether the stage's outputs exist and were made from the current inputs and conf."""
    sd = REGISTRY[stage]
    m = read_marker(job, stage)
    if m is None or any(not Path(p).exists() for p in sd.outputs(job)):
        return False
    return m.get("fingerprint") == fingerprint(sd.conf(job), sd.inputs(job), job.root)


# -- stages --------------------------------------------------------------------------------------
def _aerial_sfm(job: Job, report) -> dict:
    from services import sfm
    from services.colmap_model import read_cameras_json

    cams = read_cameras_json(job.inputs["cameras"]) if job.inputs.get("cameras") else None
    if not cams or "ground" not in cams:
        ground_camera_from_exif(job)  # fail before the SfM when the ground images' intrinsics are unknown
    report(0.0, "aerial structure from motion")
    sfm.main(job.sfm_conf(), job.image_dir, job.sfm.dir, job.pos, cams, image_set="aerial")
    write_job_cameras(job)
    rep = json.loads((job.sfm.report).read_text())
    return {"NRI": rep["NRI"], "num_points3D": rep["num_points3D"]}


def write_job_cameras(job: Job) -> Path:
    """JOB/cameras.json: the given cameras.json; else the aerial model's camera and the ground EXIF."""
    from services.colmap_model import read_cameras_json, read_model, write_cameras_json

    if job.inputs.get("cameras"):
        cams = read_cameras_json(job.inputs["cameras"])
    else:
        cams = {}
    if "aerial" not in cams:
        model_cams, _ = read_model(job.sfm.sparse)
        cams["aerial"] = next(iter(model_cams.values()))
    if "ground" not in cams:
        cams["ground"] = ground_camera_from_exif(job)
    return write_cameras_json(job.cameras, cams)


def ground_camera_from_exif(job: Job):
    """The ground camera from the first ground image's EXIF; ValueError when it has no focal length."""
    from services.pos import camera_from_exif, read_exif
    from shared.images import list_images

    ground = list_images(job.image_dir, ("ground",))
    cam = camera_from_exif(read_exif(job.image_dir / ground[0])) if ground else None
    if cam is None:
        raise ValueError("no cameras.json and no focal length in the ground images' EXIF")
    return cam


def _train_splat(job: Job, report) -> dict:
    if job.settings["renderer"] == "gt":
        out = job.splat.dir
        out.mkdir(parents=True, exist_ok=True)
        (out / "skipped.json").write_text(json.dumps({"reason": "renderer gt: no 3DGS model needed"}))
        return {"skipped": "renderer gt"}
    return train_splat(
        job.splat_conf(),
        job.sfm.sparse,
        job.image_dir,
        job.splat.dir,
        job.settings["splat_backend"],
        report,
    )


def splat_inputs_digest(sparse: Path, names: list[str], image_dir: Path) -> str:
    """sha256 of the sparse model's files (contents) and the training images' names and sizes: what the
    checkpoints of a 3DGS training were made from (contents, not times, so it holds across copies)."""
    h = hashlib.sha256()
    for f in sorted(p for p in Path(sparse).iterdir() if p.is_file()):
        h.update(f.name.encode())
        h.update(hashlib.sha256(f.read_bytes()).digest())
    for n in sorted(names):
        p = Path(image_dir) / n
        h.update(f"{n}:{p.stat().st_size if p.exists() else -1}".encode())
    return h.hexdigest()


def train_splat(
    conf: dict, sparse: Path, image_dir: Path, out: Path, backend: str, report, prefix: str = "aerial/"
) -> dict:
    """services.splat training on the registered images of `sparse` named `prefix`* in chunks
    (checkpoint at each), so that progress can be reported and a killed run resumes from its last
    chunk."""
    from services.splat import Trainer, load_scene
    from services.splat.train import write_views

    out.mkdir(parents=True, exist_ok=True)
    data = load_scene(sparse, image_dir, conf["max_width"], prefix, conf["test_every"])
    trainer = Trainer(conf, data, out, backend)
    conf_file, inputs_file = out / "conf.json", out / "inputs.sha256"
    inputs = splat_inputs_digest(sparse, [v.name for v in data.views], image_dir)
    same_conf = conf_file.is_file() and json.loads(conf_file.read_text()) == json.loads(
        json.dumps(trainer.conf)
    )
    same_inputs = inputs_file.is_file() and inputs_file.read_text().strip() == inputs
    if not (same_conf and same_inputs):  # checkpoints of another conf or another model: start afresh
        shutil.rmtree(out / "ckpts", ignore_errors=True)
    conf_file.write_text(json.dumps(trainer.conf, indent=1))
    inputs_file.write_text(inputs + "\n")
    write_views(data.views, out / "views.json")
    chunk = int(trainer.conf["ckpt_every"])
    t0 = time.perf_counter()
    done = 0
    while done < trainer.total_steps:  # conf["steps"], or fewer within conf["time_budget_s"]
        trainer.train(resume=True, stop_after=min(done + chunk, trainer.total_steps), progress=False)
        done, steps = trainer.step, trainer.total_steps
        if not (out / "ckpts" / f"step_{done:06d}.pt").is_file():
            # the chunk ended off the checkpoint grid (the time budget moved the run's end during it):
            # the next chunk resumes from here, not from the last checkpoint before it
            trainer.save_checkpoint()
        report(done / steps, f"step {done}/{steps}, {len(trainer.splats['means'])} Gaussians")
    train_s = time.perf_counter() - t0
    trainer.export()
    test = trainer.evaluate() if data.test_ids else {"psnr": float("nan"), "ssim": float("nan"), "n_views": 0}
    metrics = {
        "steps": trainer.step,
        "steps_planned": int(trainer.conf["steps"]),  # more than "steps" when the time budget cut the run
        "time_budget_s": trainer.conf["time_budget_s"],
        "num_gaussians": len(trainer.splats["means"]),
        "backend": trainer.backend,
        "resolution": [data.views[0].width, data.views[0].height],
        "seconds": {"train": train_s},
        "test": {k: test[k] for k in ("psnr", "ssim", "depth_err", "n_views") if k in test},
        "num_views": {s: sum(v.name.startswith(f"{s}/") for v in data.views) for s in ("aerial", "ground")},
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return {"num_gaussians": metrics["num_gaussians"], "test_psnr": test.get("psnr")}


def _splat_all(job: Job, report) -> dict:
    """The 3DGS on all registered images of the combined model (aerial and ground), as the paper's last
    step: the same trainer and conf as train_splat, whatever the renderer of the views."""
    return train_splat(
        job.splat_conf(),
        job.combined.sparse,
        job.image_dir,
        job.splat_all.dir,
        job.settings["splat_backend"],
        report,
        prefix="",
    )


def _plan_views(job: Job, report) -> dict:
    from services.views import planning, rendering

    report(0.0, "planning views")
    r = job.renderer(blocks=False)
    try:
        path = planning.main(
            job.viewpoint_conf(),
            job.sfm.sparse,
            job.pos,
            job.cameras,
            job.sfm.georef,
            job.plan.views,
            depth_fn=rendering.depth_fn(r),
        )
    except planning.NoViews as e:  # the plan in place (if any) stays
        raise StageError(str(e)) from e
    return json.loads(path.read_text())["summary"]


def _render_views(job: Job, report) -> dict:
    from services.views import rendering

    r = job.renderer()
    path = rendering.main(job.settings["views"], job.plan.views, job.views.dir, r, report)
    doc = json.loads(path.read_text())
    _prune(job.views.dir, {f for v in doc["views"] for f in (v["image"], v["depth"])} | {"views.json"})
    return {"num_views": len(doc["views"]), "renderer": doc["rendered"]["renderer"]}


def _prune(folder: Path, keep: set[str]) -> None:
    """Remove files of views that are no longer planned."""
    for p in folder.iterdir():
        if p.is_file() and p.name not in keep:
            p.unlink()


def view_names(job: Job) -> list[str]:
    """The rendered views (units of the match_views stage)."""
    doc = json.loads((job.views.doc).read_text())
    return [v["name"] for v in doc["views"]]


def prepare_match_views(job: Job) -> Path:
    """Extract the features of the candidate aerial and ground images once (before the fan-out), and
    of every aerial image of the model when the reducer completes aerial tracks."""
    from services.matching import views as mv

    doc = json.loads((job.views.doc).read_text())
    names = {n for v in doc["views"] for n in (*v.get("aerial", []), *v.get("ground", []))}
    if job.transfer_conf()["tracks"]["enabled"]:
        from services.colmap_model import read_model

        names |= set(read_model(job.sfm.sparse)[1])
    return mv.prepare_features(job.match_conf(), job.image_dir, sorted(names), job.features_path)


def match_view_unit(job: Job, name: str, report=None) -> list[Path]:
    """One unit of the match_views fan-out: match view `name` (the features must be prepared)."""
    from services.matching import views as mv

    doc = json.loads((job.views.doc).read_text())
    view = next(v for v in doc["views"] if v["name"] == name)
    return [
        mv.match_view(
            job.match_conf(), view, job.views.dir, job.image_dir, job.features_path, job.matches.dir
        )
    ]


def finish_match_views(job: Job, names: list[str]) -> dict:
    _prune(job.matches.dir, {f"{n}.h5" for n in names})
    return {"num_views": len(names)}


# -- train_blocks: block-wise 3DGS at the source resolution (services.splat.blocks) -------------
def prepare_blocks(job: Job) -> list[Path]:
    """Plan the blocks of the planned views into blocks/plan.json (kept when made from the same conf,
    views and whole-scene model). Renderer "gt" plans none."""
    from services.splat import blocks

    path = job.blocks.plan
    conf = job.blocks_conf()
    if not job.uses_blocks:
        why = "renderer gt: no 3DGS model to refine" if job.settings["renderer"] == "gt" else "block_steps 0"
        return [blocks.write_plan({"conf": conf, "blocks": [], "skipped": why}, path)]
    model = job.splat.model
    views_json = job.plan.views
    h = hashlib.sha256(json.dumps(conf, sort_keys=True).encode())
    for f in (views_json, model):
        h.update(hashlib.sha256(f.read_bytes()).digest())
    inputs = h.hexdigest()
    try:
        if json.loads(path.read_text()).get("inputs") == inputs:
            return [path]
    except (FileNotFoundError, ValueError):
        pass
    import pycolmap

    from services.splat import load_model

    views = json.loads(views_json.read_text())["views"]
    rec = pycolmap.Reconstruction(str(job.sfm.sparse))
    plan = blocks.plan_blocks(conf, load_model(model), rec, views, job.settings["splat_backend"])
    return [blocks.write_plan({**plan, "inputs": inputs}, path)]


def block_ids(job: Job) -> list[str]:
    """The planned blocks (units of the train_blocks stage)."""
    return [b["id"] for b in json.loads((job.blocks.plan).read_text())["blocks"]]


def train_block_unit(job: Job, block: str, report=None) -> list[Path]:
    """One unit of the train_blocks fan-out: train block `block` (the plan must exist)."""
    from services.splat import blocks

    out = job.blocks.dir
    blocks.train_block(
        out / "plan.json",
        block,
        job.splat.model,
        job.sfm.sparse,
        job.image_dir,
        out,
        job.settings["splat_backend"],
        report,
    )
    return [p for p in (out / block / "point_cloud.ply", out / block / "block.json") if p.is_file()]


def finish_blocks(job: Job, names: list[str]) -> dict:
    """blocks/report.json: each block's figures, and the reason of each block that was not trained."""
    out = job.blocks.dir
    docs = [json.loads((out / n / "block.json").read_text()) for n in names]
    for p in out.iterdir():  # blocks of an earlier plan
        if p.is_dir() and p.name not in names:
            shutil.rmtree(p)
    plan = json.loads((out / "plan.json").read_text())
    untrained = [{k: d[k] for k in ("id", "reason", "views")} for d in docs if not d["trained"]]
    for d in untrained:
        logger.warning(
            "block %s not trained: %s (its views render from the whole-scene 3DGS)", d["id"], d["reason"]
        )
    report = {
        "blocks": len(docs),
        "trained": sum(d["trained"] for d in docs),
        "untrained": untrained,
        "gsd_m": plan.get("gsd_m"),
        "seconds": round(sum(d.get("seconds", 0.0) for d in docs), 1),
        "per_block": [{k: v for k, v in d.items() if k != "digest"} for d in docs],
        **({"skipped": plan["skipped"]} if "skipped" in plan else {}),
    }
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return {k: report[k] for k in ("blocks", "trained", "untrained", "seconds")}


def blocks_queue(job: Job) -> str:
    """Blocks train on GPU workers when this machine's backend is CUDA, else on the cpu queue."""
    from services.splat import resolve_backend

    return "gpu" if resolve_backend(job.settings["splat_backend"]) == "cuda" else "cpu"


def _reduce(job: Job, report) -> dict:
    from services import reduce

    report(0.0, "transferring matches")
    files = sorted(job.matches.dir.glob("*.h5"))
    reduce.main(
        job.transfer_conf(),
        job.views.doc,
        files,
        job.sfm.sparse,
        job.pos,
        job.cameras,
        job.sfm.georef,
        job.transfer.dir,
        features=job.features_path,
    )
    rep = json.loads((job.transfer.report).read_text())
    return {
        "putative": rep["putative"],
        "verified": rep["verified"],
        "ground_poses_accepted": len(rep["ground_accepted"]),
    }


def combined_reconstruction(job: Job, out_dir: Path, report=None) -> Path:
    """services.sfm.combined on the job's aerial model, reducer output and features, into out_dir
    (the stage's folder, or another one); returns the model folder."""
    from services.sfm import combined as combined_sfm

    return combined_sfm.main(
        job.combined_conf(),
        job.sfm.dir,
        job.transfer.dir,
        job.features_path,
        job.match_conf(),
        job.image_dir,
        job.pos,
        job.cameras,
        out_dir,
        progress=report,
    )


def _combined_sfm(job: Job, report) -> dict:
    _set_threads(job)
    combined_reconstruction(job, job.combined.dir, report)
    rep = json.loads((job.combined.report).read_text())
    keys = ("NRI", "num_registered", "num_images", "num_points3D")
    return {k: rep[k] for k in keys if k in rep}


def _set_threads(job: Job) -> None:
    n = job.settings.get("torch_threads")
    if n:
        import torch

        torch.set_num_threads(int(n))


def _images(job: Job, s: str) -> Path:
    return job.image_dir / s


REGISTRY: dict[str, StageDef] = {
    "aerial_sfm": StageDef(
        "aerial_sfm",
        _aerial_sfm,
        lambda j: {"sfm": j.sfm_conf(), "cameras": j.inputs.get("cameras")},
        lambda j: (
            [_images(j, "aerial"), j.pos] + ([Path(j.inputs["cameras"])] if j.inputs.get("cameras") else [])
        ),
        lambda j: [
            j.sfm.sparse,
            j.sfm.georef,
            j.sfm.database,
            j.cameras,
        ],
        dirs=("sfm",),
        extra=("cameras.json",),
        artifacts=(
            ("sfm/report.json", "report"),
            ("sfm/georef.json", "georef"),
            ("sfm/cameras.geojson", "geojson"),
            ("sfm/sparse/*", "model"),
            ("cameras.json", "cameras"),
        ),
    ),
    "train_splat": StageDef(
        "train_splat",
        _train_splat,
        lambda j: (
            {"renderer": j.settings["renderer"]}
            if j.settings["renderer"] == "gt"
            else {"splat": j.splat_conf(), "backend": j.settings["splat_backend"]}
        ),
        lambda j: [j.sfm.sparse] + ([] if j.settings["renderer"] == "gt" else [_images(j, "aerial")]),
        lambda j: [j.splat.skipped if j.settings["renderer"] == "gt" else j.splat.model],
        dirs=("splat",),
        artifacts=(("splat/point_cloud.ply", "splat"), ("splat/metrics.json", "metrics")),
    ),
    "plan_views": StageDef(
        "plan_views",
        _plan_views,
        lambda j: {"viewpoints": j.viewpoint_conf(), "renderer": j.settings["renderer"]},
        lambda j: [
            j.sfm.sparse,
            j.sfm.georef,
            j.pos,
            j.cameras,
            *j.renderer_inputs(blocks=False),
        ],
        lambda j: [j.plan.views],
        dirs=("plan",),
        artifacts=(("plan/views.json", "views"),),
    ),
    "train_blocks": StageDef(
        "train_blocks",
        run_fanout("train_blocks"),
        lambda j: {
            "blocks": j.blocks_conf(),
            "renderer": j.settings["renderer"],
            "backend": j.settings["splat_backend"],
        },
        lambda j: (
            [j.plan.views, j.sfm.sparse, *j.renderer_inputs(blocks=False)]
            + ([] if j.settings["renderer"] == "gt" else [_images(j, "aerial")])
        ),
        lambda j: [j.blocks.plan, j.blocks.report],
        dirs=("blocks",),
        artifacts=(("blocks/report.json", "report"), ("blocks/plan.json", "blocks")),
        fanout=FanOut(
            prepare=prepare_blocks,
            units=block_ids,
            unit=train_block_unit,
            marker=lambda n: f"blocks/{n}/block.json",
            queue=blocks_queue,
            finish=finish_blocks,
            ready=lambda j: (j.blocks.plan).is_file(),
        ),
    ),
    "render_views": StageDef(
        "render_views",
        _render_views,
        lambda j: {
            "views": j.settings["views"],
            "renderer": j.settings["renderer"],
            "backend": j.settings["splat_backend"],
            "blocks": j.uses_blocks,
        },
        lambda j: [j.plan.views, *j.renderer_inputs()],
        lambda j: [j.views.doc],
        dirs=("views",),
        artifacts=(("views/views.json", "views"), ("views/*.png", "view")),
    ),
    "match_views": StageDef(
        "match_views",
        run_fanout("match_views"),
        lambda j: {"matching": j.match_conf()},
        lambda j: [j.views.doc, _images(j, "aerial"), _images(j, "ground")],
        lambda j: [j.matches.dir, j.features_path],
        dirs=("matches", "features"),
        fanout=FanOut(
            prepare=lambda j: [prepare_match_views(j)],
            units=view_names,
            unit=match_view_unit,
            marker=lambda n: f"matches/{n}.h5",
            queue=lambda j: "cpu",
            finish=finish_match_views,
            ready=lambda j: j.features_path.is_file(),
        ),
    ),
    "reduce": StageDef(
        "reduce",
        _reduce,
        lambda j: {"transfer": j.transfer_conf()},
        lambda j: [
            j.views.doc,
            j.matches.dir,
            j.sfm.sparse,
            j.sfm.georef,
            j.pos,
            j.cameras,
        ],
        lambda j: [j.transfer.matches, j.transfer.database, j.transfer.ground_poses, j.transfer.report],
        dirs=("transfer",),
        artifacts=(
            ("transfer/matches.h5", "matches"),  # the API's /jobs/{id}/pairs reads the newest "matches"
            ("transfer/ground_poses.json", "poses"),
            ("transfer/report.json", "report"),
            ("transfer/database.db", "colmap_database"),
        ),
    ),
    "combined_sfm": StageDef(
        "combined_sfm",
        _combined_sfm,
        lambda j: {"combined": j.combined_conf(), "matching": j.match_conf()},
        lambda j: [
            j.sfm.sparse,
            j.sfm.database,
            j.sfm.georef,
            j.transfer.matches,
            j.transfer.ground_poses,
            j.features_path,
            j.pos,
            j.cameras,
        ],
        lambda j: [j.combined.sparse, j.combined.report],
        dirs=("combined",),
        extra=("features",),  # the combined SfM extends the matching feature cache
        artifacts=(
            ("combined/report.json", "report"),
            ("combined/sparse/*", "model"),
            ("combined/georef.json", "georef"),
            ("combined/gis/*", "gis"),
        ),
    ),
    "splat_all": StageDef(
        "splat_all",
        _splat_all,
        lambda j: {"splat": j.splat_conf(), "backend": j.settings["splat_backend"]},
        lambda j: [j.combined.sparse, _images(j, "aerial"), _images(j, "ground")],
        lambda j: [j.splat_all.model, j.splat_all.metrics],
        dirs=("splat_all",),
        artifacts=(("splat_all/point_cloud.ply", "splat"), ("splat_all/metrics.json", "metrics")),
    ),
}
assert tuple(REGISTRY) == STAGES, "the registry must follow shared.job_options.STAGES"
assert {s for s, d in REGISTRY.items() if d.fanout} == FANOUT_STAGES, "shared.job_options.FANOUT_STAGES"


# -- runner --------------------------------------------------------------------------------------
class StageError(ValueError):
    """A stage cannot go on with what it was given; the message says why (the CLI exits 2 with it)."""


class StageInputsMissing(StageError):
    """A stage was asked for before the stages that make its inputs."""


def check_inputs(job: Job, stage: str) -> None:
    """Raise StageInputsMissing when an input that another stage makes does not exist yet."""
    need: dict[str, list[str]] = {}
    for p in REGISTRY[stage].inputs(job):
        if Path(p).exists():
            continue
        for other, sd in REGISTRY.items():
            if other != stage and any(
                Path(p) == Path(o) or Path(o) in Path(p).parents for o in sd.outputs(job)
            ):
                need.setdefault(other, []).append(str(Path(p).relative_to(job.root)))
                break
    if need:
        made = "; ".join(
            f"{', '.join(v)} (made by {k})"
            for k, v in sorted(need.items(), key=lambda kv: STAGES.index(kv[0]))
        )
        raise StageInputsMissing(f"stage {stage} needs {made}: run those stages first")


def run_stage(job: Job, stage: str, progress: Progress | None = None, force: bool = False) -> dict:
    """Run one stage unless it is up to date; returns its marker (with "skipped": True when skipped)."""
    sd = REGISTRY[stage]
    prog = progress or (lambda s, f, m: None)
    if not force and is_done(job, stage):
        m = read_marker(job, stage) or {}
        prog(stage, 1.0, "up to date")
        return {**m, "skipped": True}
    check_inputs(job, stage)
    prog(stage, 0.0, "started")
    t0 = time.perf_counter()
    summary = sd.run(job, lambda f, m: prog(stage, float(min(max(f, 0.0), 1.0)), m))
    missing = [str(p) for p in sd.outputs(job) if not Path(p).exists()]
    if missing:
        raise RuntimeError(f"stage {stage} finished without its outputs: {missing}")
    marker = write_marker(job, stage, summary, seconds=round(time.perf_counter() - t0, 2))
    prog(stage, 1.0, "finished")
    return {**marker, "skipped": False}


def write_marker(job: Job, stage: str, summary: Any, seconds: float) -> dict:
    """Record a finished stage (atomically): its input fingerprint, outputs, duration and summary."""
    sd = REGISTRY[stage]
    marker = {
        "stage": stage,
        "fingerprint": fingerprint(sd.conf(job), sd.inputs(job), job.root),
        "outputs": [str(p) for p in sd.outputs(job)],
        "seconds": seconds,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "summary": summary,
    }
    job.stages_dir.mkdir(parents=True, exist_ok=True)
    tmp = marker_path(job, stage).with_suffix(".json.tmp")
    tmp.write_text(json.dumps(marker, indent=1, default=str))
    tmp.replace(marker_path(job, stage))
    return marker


def mark_done(job: Job, stage: str, summary: dict | None = None) -> dict:
    """Record a stage as done with the outputs already in place (e.g. an aerial model or a 3DGS model
    made elsewhere and copied into the job folder); its marker gets the current input fingerprint."""
    sd = REGISTRY[stage]
    missing = [str(p) for p in sd.outputs(job) if not Path(p).exists()]
    if missing:
        raise FileNotFoundError(f"stage {stage}: outputs missing: {missing}")
    marker = write_marker(job, stage, {**(summary or {}), "adopted": True}, seconds=0.0)
    return marker


def run(
    job: Job | str | Path,
    stages: list[str] | None = None,
    from_stage: str | None = None,
    progress: Progress | None = None,
    force: bool = False,
) -> dict[str, dict]:
    """Run the job's stages in order (job.options.stages, or `stages`, from `from_stage` on; stages
    before it must be done). Returns {stage: marker} with "skipped" set for the stages that were up to
    date."""
    job = job if isinstance(job, Job) else Job.load(job)
    if stages is None:
        stages = job.options.stages_from(from_stage)
    elif from_stage is not None:
        stages = stages[stages.index(from_stage) :]
    unknown = [s for s in stages if s not in REGISTRY]
    if unknown:
        raise ValueError(f"unknown stages {unknown}; stages are {list(STAGES)}")
    results = {}
    for s in sorted(stages, key=STAGES.index):
        results[s] = run_stage(job, s, progress, force=force and (from_stage is None or s == from_stage))
    return results


def status(job: Job | str | Path) -> dict[str, str]:
    """{stage: "done" | "stale" | "pending"} of a job folder (optional stages only when selected or
    run)."""
    job = job if isinstance(job, Job) else Job.load(job)
    out = {}
    for s in STAGES:
        marker = read_marker(job, s)
        if marker is None and s in OPTIONAL_STAGES and s not in job.options.stages:
            continue
        if marker is None:
            out[s] = "pending"
        else:
            out[s] = "done" if is_done(job, s) else "stale"
    return out
