"""The pipeline stages over a job folder, and an in-process runner (`midview run`, and the Celery workers
stage by stage).

- registry.py: one StageDef per stage (name, queue, entry point, conf, inputs, outputs, artifacts,
  fan-out units, optional or not), from which everything else derives;
- stages.py: the stages' work; job.py: the job folder and its named paths (`job.sfm.sparse`);
- options.py: JobOptions (the API's, the CLI's and the workers'); runner.py: fingerprints, markers, run.

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

from services.pipeline.job import DEFAULT_SETTINGS, JOB_FILE, Job, parse_settings_overrides
from services.pipeline.options import (
    DEFAULT_PROFILE,
    PROFILE_HELP,
    PROFILES,
    JobOptions,
    Profile,
    Stage,
    option_specs,
)
from services.pipeline.registry import (
    DEFAULT_STAGES,
    FANOUT_STAGES,
    GROUND_STAGES,
    OPTIONAL_STAGES,
    REGISTRY,
    STAGE_QUEUES,
    STAGES,
    FanOut,
    StageDef,
)
from services.pipeline.runner import (
    DIGESTS_FILE,
    Progress,
    StageInputsMissing,
    check_inputs,
    fingerprint,
    is_done,
    mark_done,
    marker_path,
    read_marker,
    run,
    run_stage,
    status,
    write_marker,
)
from services.pipeline.stages import (
    StageError,
    combined_reconstruction,
    ground_camera_from_exif,
    set_threads,
    train_splat,
    write_job_cameras,
)

__all__ = [
    "DIGESTS_FILE",
    "DEFAULT_SETTINGS",
    "DEFAULT_STAGES",
    "FANOUT_STAGES",
    "GROUND_STAGES",
    "JOB_FILE",
    "OPTIONAL_STAGES",
    "REGISTRY",
    "STAGES",
    "STAGE_QUEUES",
    "FanOut",
    "Job",
    "JobOptions",
    "DEFAULT_PROFILE",
    "PROFILE_HELP",
    "PROFILES",
    "Profile",
    "Progress",
    "Stage",
    "StageDef",
    "StageError",
    "StageInputsMissing",
    "check_inputs",
    "combined_reconstruction",
    "fingerprint",
    "ground_camera_from_exif",
    "is_done",
    "mark_done",
    "marker_path",
    "option_specs",
    "parse_settings_overrides",
    "read_marker",
    "run",
    "run_stage",
    "set_threads",
    "status",
    "train_splat",
    "write_job_cameras",
    "write_marker",
]
