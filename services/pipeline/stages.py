"""The stages' work: one function per stage (run(job, report) -> summary) and the units of the fan-out
stages (train_blocks, match_views); services.pipeline.registry declares them."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from services.pipeline.job import Job

logger = logging.getLogger("midview.pipeline")


class StageError(ValueError):
    """A stage cannot go on with what it was given; the message says why (the CLI exits 2 with it)."""


def run_aerial_sfm(job: Job, report) -> dict:
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


def run_train_splat(job: Job, report) -> dict:
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
    from services.splat import Trainer, epochs_capped, load_scene
    from services.splat.train import write_views

    out.mkdir(parents=True, exist_ok=True)
    data = load_scene(sparse, image_dir, conf["max_width"], prefix, conf["test_every"])
    trainer = Trainer(epochs_capped(conf, len(data.train_ids)), data, out, backend)
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
        report(done / steps, f"step {done}/{steps}, {trainer.num_gaussians} Gaussians")
    train_s = time.perf_counter() - t0
    trainer.export()
    test = trainer.evaluate() if data.test_ids else {"psnr": float("nan"), "ssim": float("nan"), "n_views": 0}
    metrics = {
        "steps": trainer.step,
        "steps_planned": int(trainer.conf["steps"]),  # more than "steps" when the time budget cut the run
        "time_budget_s": trainer.conf["time_budget_s"],
        "num_gaussians": trainer.num_gaussians,
        "backend": trainer.backend,
        "resolution": [data.views[0].width, data.views[0].height],
        "seconds": {"train": train_s},
        "test": {k: test[k] for k in ("psnr", "ssim", "depth_err", "n_views") if k in test},
        "num_views": {s: sum(v.name.startswith(f"{s}/") for v in data.views) for s in ("aerial", "ground")},
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return {"num_gaussians": metrics["num_gaussians"], "test_psnr": test.get("psnr")}


def run_splat_all(job: Job, report) -> dict:
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


def run_plan_views(job: Job, report) -> dict:
    from services.views import planning, rendering

    report(0.0, "planning views")
    r = job.renderer(blocks=False, colour=False)
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


def run_render_views(job: Job, report) -> dict:
    from services.views import orthophoto, rendering

    r = job.renderer()
    path = rendering.main(job.settings["views"], job.plan.views, job.views.dir, r, report)
    doc = json.loads(path.read_text())
    _prune(job.views.dir, {f for v in doc["views"] for f in (v["image"], v["depth"])} | {"views.json"})
    report(0.99, "orthophoto")
    ortho = orthophoto.main(
        job.render_conf()["orthophoto"], r, job.sfm.sparse, job.sfm.georef, job.views.ortho
    )
    return {
        "num_views": len(doc["views"]),
        "renderer": doc["rendered"]["renderer"],
        "orthophoto": ortho is not None,
    }


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


def run_reduce(job: Job, report) -> dict:
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


def match_ground_pairs_ahead(job: Job, feature_path: Path) -> int:
    """The combined SfM's ground-ground pairs matched ahead into the job's pair cache (beside its
    features), from `feature_path`: a copy of the job's features that no stage writes (the demo's
    baselines' process, beside the pipeline). The number of pairs cached."""
    from services.sfm.combined.database import match_ground_pairs_ahead as ahead
    from services.sfm.combined.pair_cache import pair_cache_path

    mc = job.match_conf()
    cache = pair_cache_path(job.features_path, mc["matcher"])
    return ahead(job.sfm.dir, job.image_dir, feature_path, job.pos, mc, job.combined_conf(), cache)


def run_combined_sfm(job: Job, report) -> dict:
    combined_reconstruction(job, job.combined.dir, report)
    rep = json.loads((job.combined.report).read_text())
    keys = ("NRI", "num_registered", "num_images", "num_points3D", "causes")
    return {k: rep[k] for k in keys if k in rep}


def set_threads(job: Job) -> None:
    """torch's threads for the job's stages (settings["torch_threads"]; None: left as they are). On a
    2-core machine with another process beside (the demo's baselines), torch's default two threads wait
    on each other at every op: the planning of isprs-walk's views took 81-90 s on two threads, 15.8 s
    on one (docs/measurements.md)."""
    n = job.settings.get("torch_threads")
    if n:
        import torch

        torch.set_num_threads(int(n))


def images_of(job: Job, s: str) -> Path:
    return job.image_dir / s
