"""The distributed service end to end: a synthetic survey (`tiny` with two more aerial stations) uploaded
over HTTP to the API served by a uvicorn process (PostgreSQL, SeaweedFS S3, the Celery dispatcher), a job
run by a real Celery worker process through Redis, its results downloaded through their presigned S3 URLs
and compared with those of the `midview run` command on the same input; then the job rerun from
match_views with the worker's pool process killed (SIGKILL) in the middle of a view-matching task.

Both sides run with MIDVIEW_NUM_THREADS=1 (COLMAP) and torch_threads 1: with one thread every stage is
deterministic, so the results must be identical, not just close. (With several threads COLMAP's mapper
is not: the number of 3D points of `tiny` varies by a few between runs.)

The survey is `tiny`: its 2 x 2 grid of aerial stations registers all 20 aerial images and the paper
views match them.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
import types
import uuid
from pathlib import Path

import pytest
from conftest import upload_survey, wait_for_job, worker_environment
from servers import S3Server

from services.pipeline import DEFAULT_STAGES as STAGES

pytestmark = pytest.mark.slow

# small enough for the survey on 2 CPU cores (one to two minutes for the whole pipeline); every option
# but `stages` (all of them on both sides) is given, so that neither side's defaults matter
OPTIONS = {
    "sfm_features": "sift",
    "matcher": "aliked-lightglue",
    # the service's default; the views above the ground cameras show a street that a 1000-step 3DGS of
    # aerial images at 240 px barely learned and match little; the paper views match the aerial images
    "view_planner": "both",
    "views_per_ground_image": 1,
    "splat_steps": 1000,  # 300 gives views that match nothing at all
    "splat_max_width": 240,
    "block_steps": 60,  # train_blocks: a few blocks of 240 px on `tiny`, fanned out one task each
    "block_px": 240,
    "max_keypoints": 1024,
    "seed": 0,
}
JOB_TIMEOUT_S = 360
ROOT = Path(__file__).resolve().parents[1]


def midview_command() -> list[str]:
    """The `midview` console script of this environment, else the same app through `python -m`."""
    exe = Path(sys.executable).with_name("midview")
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "cli.main"]


def midview_run_args(scene: Path, out: Path, options: dict) -> list[str]:
    """`midview run` on a survey folder with the job options as flags, with one torch thread."""
    flags = [a for k, v in options.items() for a in (f"--{k.replace('_', '-')}", str(v))]
    images = scene / "images"
    return [*midview_command(), "run", str(images / "aerial"), str(images / "ground"), str(scene / "pos.csv"),
            str(out), "--cameras", str(scene / "cameras.json"), *flags,
            "--torch-threads", "1"]  # fmt: skip


@pytest.fixture(scope="module")
def service(service_settings, api_server, celery_worker, s3_server: S3Server):
    """An httpx client of the API's uvicorn process over 127.0.0.1, a new tenant, and (to look behind the
    API) the database and the storage of the service."""
    import httpx

    from api.bootstrap import create_tenant_with_key
    from shared.db import crud
    from shared.db.session import make_engine, make_sessionmaker
    from shared.storage import get_storage

    settings = service_settings
    engine = make_engine(settings.database_url)
    session = make_sessionmaker(engine)
    try:
        with session() as s:
            key = create_tenant_with_key(s, f"e2e-{uuid.uuid4().hex[:8]}", pepper=settings.api_key_pepper)
            tenant_id = crud.get_api_key(s, key, pepper=settings.api_key_pepper).tenant_id
            s.commit()
        tenant = types.SimpleNamespace(id=tenant_id, headers={"Authorization": f"Bearer {key}"})
        with httpx.Client(base_url=api_server.base_url, timeout=120) as client:
            yield types.SimpleNamespace(
                client=client,
                api=api_server,
                s3=s3_server,
                settings=settings,
                session=session,
                storage=get_storage(settings),
                tenant=tenant,
                worker=celery_worker,
            )
    finally:
        engine.dispose()


# outputs that must be byte-identical to those of `midview run`
BYTE_EQUAL = (
    "sfm/sparse/points3D.bin",
    "sfm/sparse/images.bin",
    "splat/point_cloud.ply",
    "combined/sparse/points3D.bin",
    "transfer/ground_poses.json",
)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _match_counts(path: Path) -> dict[str, int]:
    """{'A|B': number of matches} of an HDF5 match file."""
    from shared.matchfile import MatchFile

    with MatchFile(path) as mf:
        return {f"{pm.name0}|{pm.name1}": int(len(pm.matches)) for pm in mf.iter_pairs()}


def _service_view_matches(service, job_id: str, folder: Path) -> dict[str, dict[str, int]]:
    """Per-view match counts of the job's matches/VIEW.h5 objects (read behind the API, from storage)."""
    from shared.storage.keys import job_prefix
    from workers.jobsync import files_key

    with service.session() as s:
        from shared.db.models import Job

        row = s.get(Job, job_id)
        prefix = job_prefix(row.project.tenant_id, row.project_id, row.id)
    out = {}
    for key in service.storage.list(files_key(prefix, "matches/")):
        path = service.storage.download(key, folder / key.rsplit("/", 1)[-1])
        out[path.stem] = _match_counts(path)
    return out


def _artifacts(service, job_id: str) -> dict[str, dict]:
    """{name: artifact} of GET /jobs/{id}/artifacts."""
    r = service.client.get(f"/jobs/{job_id}/artifacts", headers=service.tenant.headers)
    assert r.status_code == 200, r.text
    return {a["name"]: a for a in r.json()}


def _download(service, job_id: str, name: str, dest: Path) -> Path:
    """The artifact's bytes from its presigned S3 URL (a plain GET, no API key), checked against the
    size and sha256 the API lists."""
    import httpx

    art = _artifacts(service, job_id)[name]
    url = art["download_url"]
    assert url.startswith(f"{service.s3.endpoint_url}/") and "X-Amz-Signature=" in url, url
    r = httpx.get(url, timeout=120)
    assert r.status_code == 200, (url, r.text[:1000])
    assert len(r.content) == art["size_bytes"] and hashlib.sha256(r.content).hexdigest() == art["sha256"]
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_bytes(r.content)
    return dest


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    """`tiny` (seed 0): 20 aerial and 4 ground images."""
    from services import synth

    return synth.main(synth.confs["tiny"], tmp_path_factory.mktemp("survey") / "tiny", seed=0)


@pytest.fixture(scope="module")
def first_run(service, survey, tmp_path_factory):
    """The job through the service and, at the same time, `midview run` on the same survey folder."""
    folder = tmp_path_factory.mktemp("e2e")
    local_root = folder / "local"
    env = worker_environment(service.settings, folder / "unused")  # MIDVIEW_NUM_THREADS=1 as the worker
    t_local = time.monotonic()
    with open(folder / "local.log", "wb") as log:
        local = subprocess.Popen(
            midview_run_args(survey, local_root, OPTIONS),
            cwd=ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    try:
        c, h = service.client, service.tenant.headers
        t0 = time.monotonic()
        pid = upload_survey(c, service.tenant, survey, service.storage)
        t_upload = time.monotonic() - t0
        r = c.post(f"/projects/{pid}/jobs", json={"options": OPTIONS}, headers=h)
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]
        seen: list = []
        t0 = time.monotonic()
        job = wait_for_job(c, h, job_id, JOB_TIMEOUT_S, seen)
        t_service = time.monotonic() - t0
        local.wait(timeout=JOB_TIMEOUT_S)
        t_local = time.monotonic() - t_local
    finally:
        if local.poll() is None:
            local.kill()
    local_log = (folder / "local.log").read_text(errors="replace")
    assert local.returncode == 0, local_log[-3000:]
    assert "combined model: NRI" in local_log, local_log[-3000:]
    # what `midview run` recorded of each stage (JOB/stages/STAGE.json), as pipeline.run returns it
    local_summaries = {
        stage: json.loads((local_root / "stages" / f"{stage}.json").read_text())["summary"]
        for stage in STAGES
    }
    print(
        f"\nupload {t_upload:.1f} s, service job {t_service:.1f} s, local run {t_local:.1f} s (in parallel)"
    )
    return types.SimpleNamespace(
        job_id=job_id,
        job=job,
        seen=seen,
        local_root=local_root,
        local_summaries=local_summaries,
        folder=folder,
    )


def test_job_succeeds_with_every_stage(service, first_run):
    job = first_run.job
    assert job["status"] == "succeeded", (job, service.worker.text()[-5000:])
    assert [st["stage"] for st in job["stages"]] == list(STAGES)
    assert all(st["status"] == "succeeded" for st in job["stages"]), job["stages"]
    assert set(job["metrics"]) == {*STAGES, "outcome"} and set(job["timings"]) == set(STAGES)
    out = job["outcome"]  # what the user got, from the combined reconstruction
    assert out == job["metrics"]["outcome"] and out["from_stage"] == "combined_sfm"
    assert out["registered"] == job["metrics"]["combined_sfm"]["num_registered"]
    assert out["result"] == ("ok" if out["registered"] == out["images"] else "warnings")
    assert job["progress"] == 1.0
    stages_seen = [st for _, st, _ in first_run.seen if st]
    assert stages_seen and stages_seen[-1] == "combined_sfm"
    assert {"match_views", "train_splat"} <= set(stages_seen)
    arts = {name: a["kind"] for name, a in _artifacts(service, first_run.job_id).items()}
    for name, kind in [
        ("sfm/report.json", "report"),
        ("splat/point_cloud.ply", "splat"),
        ("blocks/report.json", "report"),
        ("transfer/matches.h5", "matches"),
        ("transfer/ground_poses.json", "poses"),
        ("combined/report.json", "report"),
        ("combined/sparse/images.bin", "model"),
    ]:
        assert arts.get(name) == kind, (name, arts)


def test_results_equal_the_local_run(service, first_run):
    """Same registered images, same 3D points, same views, same matches per pair as `midview run`; the
    models downloaded from the service are the same bytes as its files."""
    job, local = first_run.job, first_run.local_summaries
    # the command ran the job the service ran: same options
    assert json.loads((first_run.local_root / "job.json").read_text())["options"] == job["options"]
    print("service:", json.dumps(job["metrics"]))
    print("local:  ", json.dumps(local))
    folder = first_run.folder / "service"
    lr = first_run.local_root

    sfm = json.loads(_download(service, first_run.job_id, "sfm/report.json", folder / "sfm.json").read_text())
    local_sfm = json.loads((lr / "sfm" / "report.json").read_text())
    assert sfm["NRI"] == local_sfm["NRI"] and sfm["num_points3D"] == local_sfm["num_points3D"]

    combined = json.loads(
        _download(service, first_run.job_id, "combined/report.json", folder / "c.json").read_text()
    )
    local_combined = json.loads((lr / "combined" / "report.json").read_text())
    assert combined["num_registered"] == local_combined["num_registered"]
    assert combined["num_points3D"] == local_combined["num_points3D"]

    assert job["metrics"]["plan_views"] == local["plan_views"]
    assert job["metrics"]["train_splat"]["num_gaussians"] == local["train_splat"]["num_gaussians"]
    assert job["metrics"]["reduce"] == local["reduce"]
    # the blocks trained as unit tasks are those `midview run` trained in-process
    assert job["metrics"]["train_blocks"]["trained"] == local["train_blocks"]["trained"] >= 2
    blocks = json.loads(
        _download(service, first_run.job_id, "blocks/report.json", folder / "b.json").read_text()
    )
    local_blocks = json.loads((lr / "blocks" / "report.json").read_text())
    # an untrained block (no aerial image sees it) has its reason, no figures: it compares by those
    keys = ("id", "trained", "reason", "crops", "steps", "gaussians", "psnr_after")
    assert [{k: b.get(k) for k in keys} for b in blocks["per_block"]] == [
        {k: b.get(k) for k in keys} for b in local_blocks["per_block"]
    ]

    views = _service_view_matches(service, first_run.job_id, folder / "matches")
    local_views = {p.stem: _match_counts(p) for p in sorted((lr / "matches").glob("*.h5"))}
    print("views:", views)
    assert views == local_views and views and sum(sum(v.values()) for v in views.values()) > 0

    # the models are the same bytes: the sha256 the API lists and the bytes downloaded
    arts = _artifacts(service, first_run.job_id)
    same = {name: arts[name]["sha256"] == _sha256(lr / name) for name in BYTE_EQUAL}
    print("same bytes:", same)
    assert all(same.values()), same
    for name in BYTE_EQUAL:
        got = _download(service, first_run.job_id, name, folder / "files" / name)
        assert got.read_bytes() == (lr / name).read_bytes(), name

    h5 = _download(service, first_run.job_id, "transfer/matches.h5", folder / "transfer.h5")
    assert _match_counts(h5) == _match_counts(lr / "transfer" / "matches.h5")
    pairs = service.client.get(f"/jobs/{first_run.job_id}/pairs", headers=service.tenant.headers).json()
    assert pairs["artifact"] == "transfer/matches.h5"
    assert pairs["total"] == len(_match_counts(h5))  # the reducer's pairs are all aerial-ground


def _kill_match_view_midway(redis_client, job_id: str, job_dir: Path, timeout_s: float) -> dict | None:
    """SIGKILL the pool process running a match_views unit task of the job while it writes its match file
    (matches/VIEW.h5.tmp exists in the worker's job folder: past the sync, in the matching)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        running = []
        for key in redis_client.scan_iter("midview:task:*:alive", count=500):
            raw = redis_client.get(key)
            info = json.loads(raw) if raw else {}
            unit = info.get("task") == "midview.stage_unit" and info.get("args", [None])[1:2] == [
                "match_views"
            ]
            if info.get("job") == job_id and unit:
                info["task_id"] = key.decode().split(":")[2]
                running.append(info)
        while running and time.monotonic() < deadline:
            writing = {p.name[: -len(".h5.tmp")] for p in (job_dir / "matches").glob("*.h5.tmp")}
            hit = [i for i in running if i["args"][2] in writing]
            if hit:
                os.kill(int(hit[0]["pid"]), signal.SIGKILL)
                hit[0]["killed_after_s"] = time.time() - hit[0]["started"]
                return hit[0]
            if not any(redis_client.exists(f"midview:task:{i['task_id']}:alive") for i in running):
                break  # finished before we saw it matching: wait for the next one
            time.sleep(0.003)
        time.sleep(0.01)
    return None


def test_killed_worker_process_mid_matching(service, first_run):
    """Rerun from match_views (its outputs deleted, so that every view is matched again) and SIGKILL the
    pool process during a match_views unit task: the message is requeued (acks_late + reject_on_worker_lost),
    matched again by a new pool process, and the job ends with the same results as before."""
    import redis

    from shared.db.models import Job
    from shared.storage.keys import job_prefix
    from workers.jobsync import files_key

    assert first_run.job["status"] == "succeeded"
    c, h, job_id = service.client, service.tenant.headers, first_run.job_id
    with service.session() as s:
        row = s.get(Job, job_id)
        prefix = job_prefix(row.project.tenant_id, row.project_id, row.id)
    for key in [
        *service.storage.list(files_key(prefix, "matches/")),
        files_key(prefix, "stages/match_views.json"),
    ]:
        service.storage.delete(key)

    rd = redis.Redis.from_url(service.settings.broker_url)
    t0 = time.monotonic()
    r = c.post(f"/jobs/{job_id}/rerun", json={"from_stage": "match_views"}, headers=h)
    assert r.status_code == 200, r.text
    killed = _kill_match_view_midway(rd, job_id, service.worker.work_dir / job_id, 120)
    assert killed is not None, service.worker.text()[-5000:]
    print(f"\nkilled pool process {killed['pid']} {killed['killed_after_s']:.1f} s into {killed['args']}")
    job = wait_for_job(c, h, job_id, JOB_TIMEOUT_S)
    print(f"\nrerun from match_views with a killed pool process: {time.monotonic() - t0:.1f} s")
    log = service.worker.text()
    assert job["status"] == "succeeded", (job, log[-5000:])
    assert job["attempt"] == 2
    # the process died with the task unfinished; its message came back and succeeded in another process
    lost = log.find(f"pid:{killed['pid']} exited with 'signal 9 (SIGKILL)'")
    done = log.find(f"Task midview.stage_unit[{killed['task_id']}] succeeded")
    assert 0 <= lost < done, log[-5000:]
    # match_views ran again, then the reducer; its outputs are the first run's byte for byte, so the
    # combined reconstruction, whose fingerprint is made of its inputs' contents, is up to date
    assert [st["stage"] for st in job["stages"] if st["status"] == "succeeded"][-2:] == [
        "match_views", "reduce"]  # fmt: skip
    assert [st["status"] for st in job["stages"] if st["stage"] == "combined_sfm"][-1] == "skipped"
    assert all(
        job["metrics"][s] == first_run.job["metrics"][s] for s in ("match_views", "reduce", "combined_sfm")
    )

    folder = first_run.folder / "rerun"
    views = _service_view_matches(service, job_id, folder / "matches")
    local_views = {p.stem: _match_counts(p) for p in sorted((first_run.local_root / "matches").glob("*.h5"))}
    assert views == local_views
    h5 = _download(service, job_id, "transfer/matches.h5", folder / "transfer.h5")
    assert _match_counts(h5) == _match_counts(first_run.local_root / "transfer" / "matches.h5")


def test_rerun_on_an_empty_worker_folder_skips_every_stage(service, first_run):
    """As if another worker took the job: its local job folder is deleted, a rerun of the whole job pulls
    everything from storage, and every stage is up to date (the fingerprints are made of contents)."""
    import shutil

    c, h, job_id = service.client, service.tenant.headers, first_run.job_id
    before = c.get(f"/jobs/{job_id}", headers=h).json()
    assert before["status"] == "succeeded"
    shutil.rmtree(service.worker.work_dir / job_id)
    t0 = time.monotonic()
    r = c.post(f"/jobs/{job_id}/rerun", headers=h)
    assert r.status_code == 200, r.text
    job = wait_for_job(c, h, job_id, JOB_TIMEOUT_S)
    print(f"\nrerun with every stage up to date, from an empty job folder: {time.monotonic() - t0:.1f} s")
    assert job["status"] == "succeeded", (job, service.worker.text()[-5000:])
    runs = [(st["stage"], st["status"]) for st in job["stages"]][-len(STAGES) :]
    assert runs == [(s, "skipped") for s in STAGES], runs
    assert job["metrics"] == before["metrics"]
