"""A job created through the API with no options on a CPU-only deployment: what a team waits for.

    python bench/api_job.py --preset tiny [--seed 0] [--no-reference] [--json docs/results/api-job.json]

Synthesizes the preset (kept under runs/bench/api-PRESET-seedN/scene when complete; not timed), starts
`midview serve` on its embedded defaults (SQLite, a local storage folder, the in-process worker, which
offers the `cpu` profile) in a throwaway folder, submits the survey with the Python client
(client.submit_survey: uploads, POS, cameras) and creates the job with **no options**, then follows it
to its end. Reports the upload seconds, the job's seconds from its creation to its end, each stage's
seconds (the API's stage runs), the profile and options the job got, and the ground images registered.
With the reference (default), the same survey is then run in-process the way `midview run` runs it
(services.pipeline.run with the `cpu` profile's defaults), one after the other on the same machine: the
ratio says what the service adds to the pipeline.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import servers  # noqa: E402  (tests/servers.py: start_midview_serve, _stop)

from client import MidviewClient, Survey, submit_survey  # noqa: E402
from services import pipeline, synth  # noqa: E402
from shared.config import Settings  # noqa: E402

TEXTURES = ROOT.parent / "shared" / "data" / "lund_street"
API_KEY = "mv_bench_api_job_key_0001"
TERMINAL = {"succeeded", "failed", "canceled", "cancelled"}


def survey_scene(preset: str, seed: int) -> Path:
    """The synthesized survey (made once, then reused)."""
    scene = ROOT / "runs" / "bench" / f"api-{preset}-seed{seed}" / "scene"
    if not synth.scene_complete(scene):
        textures = TEXTURES if TEXTURES.is_dir() else None
        synth.main(synth.confs[preset], scene, seed=seed, textures_dir=textures, overwrite=True)
    return scene


def through_api(scene: Path, work: Path, timeout_s: float) -> dict[str, Any]:
    """Serve, submit with no options, follow the job to its end: the figures of the run."""
    threads = str(Settings.model_fields["num_threads"].default)  # what a plain `midview serve` uses
    proc, base = servers.start_midview_serve(
        work / "data", API_KEY, work / "serve.log", env_extra={"MIDVIEW_NUM_THREADS": threads}
    )
    try:
        images = scene / "images"
        survey = Survey(
            name=f"bench-{scene.parent.name}", aerial=images / "aerial", ground=images / "ground",
            pos=scene / "pos.csv", cameras=scene / "cameras.json", options={},
        )  # fmt: skip
        with MidviewClient(base, API_KEY) as mv:
            t0 = time.perf_counter()
            job = submit_survey(mv, survey)
            created = time.perf_counter()
            last = ""
            while job["status"] not in TERMINAL:
                if time.perf_counter() - created > timeout_s:
                    raise TimeoutError(f"job {job['id']} still {job['status']} after {timeout_s} s")
                time.sleep(1.0)
                job = mv.job(job["id"])
                line = f"{job['current_stage'] or '-'} {job['progress_percent']:.0f}%"
                if line != last:
                    print(f"[{time.perf_counter() - created:6.1f} s] {line}", flush=True)
                    last = line
            ended = time.perf_counter()
        if job["status"] != "succeeded":
            raise RuntimeError(
                f"job {job['id']} {job['status']}: {job.get('error')}\n{servers._tail(work / 'serve.log')}"
            )
        stages = {
            s["stage"]: s["duration_s"] for s in job.get("stages", []) if s.get("duration_s") is not None
        }
        outcome = job.get("outcome") or {}
        return {
            "upload_s": round(created - t0, 1),
            "job_s": round(ended - created, 1),
            "job_min": round((ended - created) / 60, 2),
            "stages_s": {k: round(float(v), 1) for k, v in stages.items()},
            "profile": job["options"].get("profile"),
            "options": job["options"],
            "ground_registered": (outcome.get("registered") or {}).get("ground"),
            "ground_total": (outcome.get("images") or {}).get("ground"),
        }
    finally:
        servers._stop(proc)


def in_process(scene: Path, work: Path, profile: str) -> dict[str, Any]:
    """The same survey through services.pipeline.run (what `midview run` runs), timed."""
    images = scene / "images"
    job = pipeline.Job.create(
        work / "job", images / "aerial", images / "ground", scene / "pos.csv", scene / "cameras.json",
        options={"profile": profile},
    )  # fmt: skip
    t0 = time.perf_counter()
    results = pipeline.run(job, progress=lambda st, f, m: None, force=True)
    total = time.perf_counter() - t0
    report = json.loads(job.combined.report.read_text()) if job.combined.report.is_file() else {}
    return {
        "job_s": round(total, 1),
        "stages_s": {st: round(float(r["seconds"]), 1) for st, r in results.items()},
        "ground_registered": (report.get("num_registered") or {}).get("ground"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="tiny", choices=sorted(synth.confs))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-reference", action="store_true", help="skip the in-process run beside")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds the job may take")
    ap.add_argument("--json", type=Path, default=None, help="append this run to a results file")
    a = ap.parse_args(argv)
    scene = survey_scene(a.preset, a.seed)
    work = Path(tempfile.mkdtemp(prefix="midview-api-job-"))
    try:
        api = through_api(scene, work, a.timeout)
        figures: dict[str, Any] = {"api": api}
        if not a.no_reference:
            ref = in_process(scene, work, api["profile"] or "cpu")
            figures["in_process"] = ref
            figures["api_over_in_process"] = round(api["job_s"] / ref["job_s"], 3)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT)
    run = {
        "command": "python bench/api_job.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "commit": commit.stdout.strip(),
        "machine": f"{os.cpu_count()} cores, {platform.machine()}",
        "preset": a.preset,
        "seed": a.seed,
        "figures": figures,
    }
    print(json.dumps(run, indent=1))
    if a.json:
        doc = json.loads(a.json.read_text()) if a.json.is_file() else {"runs": []}
        doc["runs"] = [r for r in doc["runs"] if (r["preset"], r["seed"]) != (a.preset, a.seed)] + [run]
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
