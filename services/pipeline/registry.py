"""The stage registry: one StageDef per stage, in pipeline order, and the names derived from it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from services.pipeline.stages import (
    block_ids,
    blocks_queue,
    finish_blocks,
    finish_match_views,
    images_of,
    match_view_unit,
    prepare_blocks,
    prepare_match_views,
    run_aerial_sfm,
    run_combined_sfm,
    run_plan_views,
    run_reduce,
    run_render_views,
    run_splat_all,
    run_train_splat,
    train_block_unit,
    view_names,
)

if TYPE_CHECKING:
    from services.pipeline.job import Job


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
        assert fan is not None, f"stage {stage} is not a fan-out"
        report(0.0, "preparing the units")
        fan.prepare(job)
        names = fan.units(job)
        for i, n in enumerate(names):

            def unit_report(f: float, m: str, i: int = i) -> None:
                report((i + min(max(f, 0.0), 1.0)) / len(names), m)

            fan.unit(job, n, unit_report)
            report((i + 1) / len(names), f"{n} done ({i + 1}/{len(names)})")
        return fan.finish(job, names)

    return run


@dataclass(frozen=True, kw_only=True)
class StageDef:
    """One stage, declared once: everything else (the in-process runner, the Celery canvas and queues,
    the embedded dispatcher, the artifact listing, the API's stage list and JobOptions.stages) derives
    from these declarations.

    name: the stage's name (positional); queue: the Celery queue of its tasks (gpu: SfM, 3DGS, rendering;
    cpu: per-view matching; reduce); run(job, report) -> summary dict; conf, inputs, outputs: derived
    from the job (its fingerprint is of the conf and the inputs' contents); dirs: the folders of the job
    it owns (the first its own); extra: the files it writes outside them; artifacts: its user-facing
    outputs ((path or folder/* or folder/*.ext relative to the job folder, kind)), which the workers sync,
    record and list; fanout: its independent units (one task each in the service); optional: run only
    when a job asks for it; ground: whether it works on ground images."""

    name: str = field(kw_only=False)
    queue: str
    run: Callable[[Job, Callable[[float, str], None]], dict]
    conf: Callable[[Job], Any]
    inputs: Callable[[Job], list[Path]]
    outputs: Callable[[Job], list[Path]]
    dirs: tuple[str, ...] = ()
    extra: tuple[str, ...] = ()
    artifacts: tuple[tuple[str, str], ...] = ()
    fanout: FanOut | None = None
    optional: bool = False
    ground: bool = True


DECLARATIONS: tuple[StageDef, ...] = (
    StageDef(
        "aerial_sfm",
        queue="gpu",
        ground=False,
        run=run_aerial_sfm,
        conf=lambda j: {"sfm": j.sfm_conf(), "cameras": j.inputs.get("cameras")},
        inputs=lambda j: (
            [images_of(j, "aerial"), j.pos] + ([Path(j.inputs["cameras"])] if j.inputs.get("cameras") else [])
        ),
        outputs=lambda j: [
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
    StageDef(
        "train_splat",
        queue="gpu",
        ground=False,
        run=run_train_splat,
        conf=lambda j: (
            {"renderer": j.settings["renderer"]}
            if j.settings["renderer"] == "gt"
            else {"splat": j.splat_conf(), "backend": j.settings["splat_backend"]}
        ),
        inputs=lambda j: (
            [j.sfm.sparse] + ([] if j.settings["renderer"] == "gt" else [images_of(j, "aerial")])
        ),
        outputs=lambda j: [j.splat.skipped if j.settings["renderer"] == "gt" else j.splat.model],
        dirs=("splat",),
        artifacts=(("splat/point_cloud.ply", "splat"), ("splat/metrics.json", "metrics")),
    ),
    StageDef(
        "plan_views",
        queue="gpu",
        run=run_plan_views,
        conf=lambda j: {
            "viewpoints": j.viewpoint_conf(),
            "renderer": j.settings["renderer"],
            "rendering": j.render_conf(),  # the depth probe: the plane proxy's with colour "source"
        },
        inputs=lambda j: [
            j.sfm.sparse,
            j.sfm.georef,
            j.pos,
            j.cameras,
            *j.renderer_inputs(blocks=False),
        ],
        outputs=lambda j: [j.plan.views],
        dirs=("plan",),
        artifacts=(("plan/views.json", "views"),),
    ),
    StageDef(
        "train_blocks",
        queue="gpu",  # one task per block, on the cpu queue where there is no GPU (blocks_queue)
        run=run_fanout("train_blocks"),
        conf=lambda j: {
            "blocks": j.blocks_conf(),
            "renderer": j.settings["renderer"],
            "backend": j.settings["splat_backend"],
        },
        inputs=lambda j: (
            [j.plan.views, j.sfm.sparse, *j.renderer_inputs(blocks=False)]
            + ([] if j.settings["renderer"] == "gt" else [images_of(j, "aerial")])
        ),
        outputs=lambda j: [j.blocks.plan, j.blocks.report],
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
    StageDef(
        "render_views",
        queue="gpu",
        run=run_render_views,
        conf=lambda j: {
            "views": j.settings["views"],
            "renderer": j.settings["renderer"],
            "backend": j.settings["splat_backend"],
            "blocks": j.uses_blocks,
        },
        inputs=lambda j: [j.plan.views, *j.renderer_inputs()],
        outputs=lambda j: [j.views.doc],
        dirs=("views",),
        artifacts=(
            ("views/views.json", "views"),
            ("views/*.png", "view"),
            ("views/ortho/orthophoto.tif", "orthophoto"),  # GeoTIFF, WGS84
            ("views/ortho/orthophoto.png", "orthophoto-image"),  # the map's background
            ("views/ortho/orthophoto.json", "orthophoto-bounds"),
        ),
    ),
    StageDef(
        "match_views",
        queue="cpu",
        run=run_fanout("match_views"),
        conf=lambda j: {"matching": j.match_conf()},
        inputs=lambda j: [j.views.doc, images_of(j, "aerial"), images_of(j, "ground")],
        outputs=lambda j: [j.matches.dir, j.features_path],
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
    StageDef(
        "reduce",
        queue="reduce",
        run=run_reduce,
        conf=lambda j: {"transfer": j.transfer_conf()},
        inputs=lambda j: [
            j.views.doc,
            j.matches.dir,
            j.sfm.sparse,
            j.sfm.georef,
            j.pos,
            j.cameras,
        ],
        outputs=lambda j: [
            j.transfer.matches,
            j.transfer.database,
            j.transfer.ground_poses,
            j.transfer.report,
        ],
        dirs=("transfer",),
        artifacts=(
            ("transfer/matches.h5", "matches"),  # the API's /jobs/{id}/pairs reads the newest "matches"
            ("transfer/ground_poses.json", "poses"),
            ("transfer/report.json", "report"),
            ("transfer/database.db", "colmap_database"),
        ),
    ),
    StageDef(
        "combined_sfm",
        queue="reduce",
        run=run_combined_sfm,
        conf=lambda j: {"combined": j.combined_conf(), "matching": j.match_conf()},
        inputs=lambda j: [
            j.sfm.sparse,
            j.sfm.database,
            j.sfm.georef,
            j.transfer.matches,
            j.transfer.ground_poses,
            j.features_path,
            j.pos,
            j.cameras,
        ],
        outputs=lambda j: [j.combined.sparse, j.combined.report],
        dirs=("combined",),
        extra=("features",),  # the combined SfM extends the matching feature cache
        artifacts=(
            ("combined/report.json", "report"),
            ("combined/sparse/*", "model"),
            ("combined/georef.json", "georef"),
            ("combined/gis/*", "gis"),
        ),
    ),
    StageDef(
        "splat_all",
        queue="gpu",
        optional=True,
        run=run_splat_all,
        conf=lambda j: {"splat": j.splat_conf(), "backend": j.settings["splat_backend"]},
        inputs=lambda j: [j.combined.sparse, images_of(j, "aerial"), images_of(j, "ground")],
        outputs=lambda j: [j.splat_all.model, j.splat_all.metrics],
        dirs=("splat_all",),
        artifacts=(("splat_all/point_cloud.ply", "splat"), ("splat_all/metrics.json", "metrics")),
    ),
)
REGISTRY: dict[str, StageDef] = {s.name: s for s in DECLARATIONS}
STAGES: tuple[str, ...] = tuple(REGISTRY)  # in pipeline order
# stages a job runs only when asked (in `stages`): the 3DGS on all images of the combined model
OPTIONAL_STAGES: frozenset[str] = frozenset(s.name for s in DECLARATIONS if s.optional)
DEFAULT_STAGES: tuple[str, ...] = tuple(s for s in STAGES if s not in OPTIONAL_STAGES)
# the Celery queue of each stage's tasks
STAGE_QUEUES: dict[str, str] = {s.name: s.queue for s in DECLARATIONS}
# stages made of independent units, one task each: their first task prepares the units and fans them
# out, a last run of the stage checks and summarises them
FANOUT_STAGES: frozenset[str] = frozenset(s.name for s in DECLARATIONS if s.fanout)
# stages that need ground images (everything after the aerial-only part)
GROUND_STAGES: frozenset[str] = frozenset(s.name for s in DECLARATIONS if s.ground)
