"""A job folder: its inputs, options and settings, and the named paths of every stage's files."""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from services.conf import merge_conf
from services.pipeline.options import JobOptions

logger = logging.getLogger("midview.pipeline")
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
    splat: list[str],
    viewpoints: list[str],
    matching: list[str],
    matcher: str = "aliked-lightglue",
    rendering: Sequence[str] = (),
) -> dict[str, dict]:
    """`KEY=VALUE` strings of the 3DGS, viewpoint, matching (the matcher's) and rendering confs -> the
    job settings that override them (services.conf.parse_overrides: ValueError with the reason)."""
    from services.conf import parse_overrides
    from services.matching.views import confs as match_confs
    from services.splat import confs as splat_confs
    from services.splat.train import check_conf
    from services.views import confs as view_confs
    from services.views import rendering as view_rendering

    render_over = parse_overrides(list(rendering), view_rendering.confs["default"])
    if render_over.get("colour", "source") not in ("source", "splat"):
        raise ValueError(f"colour must be source or splat, not {render_over['colour']!r}")
    splat_over = parse_overrides(splat, splat_confs["fast"])
    check_conf(merge_conf(splat_confs["fast"], splat_over))
    return {
        "splat": splat_over,
        "viewpoints": parse_overrides(viewpoints, view_confs["both"]),
        "matching": parse_overrides(matching, match_confs.get(matcher, match_confs["aliked-lightglue"])),
        "views": render_over,
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

    dir: Path

    def __init__(self, path: Path) -> None:
        self.dir = path

    def __truediv__(self, name: str) -> Path:
        return self.dir / name

    def glob(self, pattern: str) -> list[Path]:
        return sorted(self.dir.glob(pattern))


class SfmFolder(Folder):
    sparse: _File = _File("sparse")
    georef: _File = _File("georef.json")
    database: _File = _File("database.db")
    report: _File = _File("report.json")


class SplatFolder(Folder):
    model: _File = _File("point_cloud.ply")
    metrics: _File = _File("metrics.json")
    skipped: _File = _File("skipped.json")


class PlanFolder(Folder):
    views: _File = _File("views.json")


class BlocksFolder(Folder):
    plan: _File = _File("plan.json")
    report: _File = _File("report.json")


class ViewsFolder(Folder):
    doc: _File = _File("views.json")
    ortho: _File = _File("ortho")  # services.views.orthophoto's files


class TransferFolder(Folder):
    matches: _File = _File("matches.h5")
    ground_poses: _File = _File("ground_poses.json")
    database: _File = _File("database.db")
    report: _File = _File("report.json")


class CombinedFolder(Folder):
    sparse: _File = _File("sparse")
    georef: _File = _File("georef.json")
    report: _File = _File("report.json")


class Job:
    """A job folder: inputs, options, settings and the paths of every stage's files."""

    root: Path
    inputs: dict[str, Any]
    options: JobOptions
    settings: dict[str, Any]

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
        inputs: dict[str, Any] = {
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
        over: dict[str, Any] = {
            "mapping": {"seed": self.options.seed},
            "matching": {"num_neighbors": int(self.options.sfm_neighbors)},
        }
        if base["features"]["type"] == "sift":
            over["features"] = {
                "max_image_size": int(self.options.sfm_max_image_size),
                "max_num_features": int(self.options.sfm_max_features),
            }
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
            "strategy": {"max_gaussians": int(self.options.splat_max_gaussians)},
        }
        if self.options.splat_time_budget_s is not None:
            over["time_budget_s"] = float(self.options.splat_time_budget_s)
        if self.options.splat_epochs is not None:
            over["max_epochs"] = float(self.options.splat_epochs)
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
    def renderer(self, blocks: bool = True, colour: bool = True):
        """The views' renderer: the trained blocks over the whole-scene 3DGS when the job has them (and
        `blocks`), else the whole-scene 3DGS, or the ground truth (renderer "gt"); with the views' conf
        colour "source", its depth fused with the plane proxy and (with `colour`) its views coloured from
        the aerial images (SourceRenderer)."""
        from services import views

        if self.settings["renderer"] == "gt":
            if not self.settings.get("scene"):
                raise ValueError("renderer 'gt' needs settings.scene: a synthetic scene folder")
            return views.GroundTruthRenderer(self.settings["scene"], self.sfm.sparse)
        if self.settings["renderer"] != "splat":
            raise ValueError(f"unknown renderer {self.settings['renderer']!r} (splat, gt)")
        conf = self.render_conf()
        if not colour and conf["plan_depth"] != "same":  # the planner's probes on another depth (bench)
            conf = {**conf, "depth": conf["plan_depth"]}
        min_alpha = conf["min_alpha"]
        if blocks and self.uses_blocks and (self.blocks.report).is_file():
            from services.views import BlockRenderer

            backend = self.settings["splat_backend"]
            base: Any = BlockRenderer(self.splat.dir, self.blocks.dir, backend, min_alpha)
        else:
            base = views.SplatRenderer(self.splat.dir, self.settings["splat_backend"], min_alpha)
        if conf["colour"] == "source":  # without colour: the planes' depth for the planner's probes
            return views.SourceRenderer(
                base,
                self.sfm.sparse,
                self.image_dir,
                conf,
                colour=colour,
                cache_dir=self.root / "stereo",
                scene=self.settings.get("scene"),
            )
        return base

    def render_conf(self) -> dict:
        """services.views.rendering's conf with the job's overrides (settings "views")."""
        from services.views import rendering

        return merge_conf(rendering.confs["default"], self.settings["views"])

    def renderer_inputs(self, blocks: bool = True) -> list[Path]:
        if self.settings["renderer"] == "gt":
            return [Path(self.settings["scene"]) / "gt" / "scene.json"]
        own = [self.blocks.plan, self.blocks.report]
        sources = [self.sfm.sparse / "points3D.bin", self.sfm.sparse / "images.bin"]
        return [
            self.splat.model,
            *(own if blocks and self.uses_blocks else []),
            *(sources if self.render_conf()["colour"] == "source" else []),
        ]
