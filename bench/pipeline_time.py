"""The stages of `midview run` on a synthetic survey, timed, against the seed paper's GPU 3DGS alone.

    python bench/pipeline_time.py --preset isprs [--seed 0] [--profile cpu] [--out runs/bench/time-isprs]
        [--json docs/results/pipeline-time.json]

Synthesizes the preset (kept when complete; not counted), then runs every default stage of `midview run`
in-process with the job profile's defaults (what `midview run`, the demo and the API's CPU workers run),
and reports each stage's seconds, the total, the ground images registered, and the total against the
seed paper's 3DGS training alone (Tables 4 and 7: 14-28 minutes per dataset on an RTX 4090), and the
cost model's prediction for this survey (services.pipeline.costs) with its error. Machine-dependent:
compare figures measured on the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services import pipeline, synth  # noqa: E402
from services.pipeline import costs  # noqa: E402

PAPER_3DGS_MIN = (14.0, 28.0)  # the seed paper's 3DGS training per dataset, RTX 4090 (Tables 4 and 7)
TEXTURES = ROOT.parent / "shared" / "data" / "lund_street"


def survey_size(scene: Path) -> dict[str, int]:
    images = scene / "images"
    return {s: sum(1 for p in (images / s).iterdir() if p.is_file()) for s in ("aerial", "ground")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="isprs", choices=sorted(synth.confs))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", default="cpu", choices=sorted(pipeline.PROFILES))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None, help="append this run to a results file")
    ap.add_argument(
        "--fit", action="store_true", help="fit the cost model on the runs of --json; run nothing"
    )
    a = ap.parse_args(argv)
    if a.fit:
        doc = json.loads(a.json.read_text())
        doc["fit"] = costs.fit_runs(doc["runs"])
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
        print(json.dumps(doc["fit"], indent=1))
        return 0
    out = a.out or ROOT / "runs" / "bench" / f"time-{a.preset}-seed{a.seed}"
    scene = out / "scene"
    if not synth.scene_complete(scene):
        textures = TEXTURES if TEXTURES.is_dir() else None
        synth.main(synth.confs[a.preset], scene, seed=a.seed, textures_dir=textures, overwrite=True)
    images = scene / "images"
    job = pipeline.Job.create(
        out / "job", images / "aerial", images / "ground", scene / "pos.csv", scene / "cameras.json",
        options={"profile": a.profile, "seed": a.seed},
    )  # fmt: skip
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT)
    size = survey_size(scene)
    predicted = costs.estimate(job.options, size["aerial"], size["ground"])
    t0 = time.perf_counter()
    results = pipeline.run(job, progress=lambda st, f, m: None, force=True)
    total = time.perf_counter() - t0
    stages = {st: round(float(r["seconds"]), 1) for st, r in results.items()}
    report = json.loads(job.combined.report.read_text()) if job.combined.report.is_file() else {}
    guess = predicted["stages_s"]
    errors = {st: round(guess[st] / s - 1.0, 3) for st, s in stages.items() if s > 0 and guess.get(st)}
    run = {
        "preset": a.preset,
        "seed": a.seed,
        "profile": a.profile,
        "survey": size,
        "options": job.options.model_dump(mode="json"),
        "stages_s": stages,
        "total_s": round(total, 1),
        "total_min": round(total / 60, 1),
        "ground_registered": (report.get("num_registered") or {}).get("ground"),
        "paper_3dgs_min": list(PAPER_3DGS_MIN),
        "total_over_paper_3dgs": [round(total / 60 / m, 2) for m in PAPER_3DGS_MIN],
        "cost_model": {
            "predicted_s": predicted["stages_s"],
            "predicted_total_s": predicted["total_s"],
            "relative_error": errors,
            "total_relative_error": round(predicted["total_s"] / total - 1.0, 3)
            if predicted["total_s"]
            else None,
        },
    }
    print(json.dumps(run, indent=1))
    if a.json:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
        )
        doc = json.loads(a.json.read_text()) if a.json.is_file() else {}
        doc.setdefault("runs", [])
        doc["runs"] = [
            r for r in doc["runs"] if (r["preset"], r["seed"], r["profile"]) != (a.preset, a.seed, a.profile)
        ]
        doc["runs"].append(
            {**run, "command": "python bench/pipeline_time.py " + " ".join(argv or sys.argv[1:]),
             "commit": commit.stdout.strip(), "machine": f"{os.cpu_count()} cores, {platform.machine()}"}
        )  # fmt: skip
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
