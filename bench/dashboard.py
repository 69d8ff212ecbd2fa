"""Dashboard benchmark: how long the job page, the map and a ground image's page take to show a job of N
images (default 200), in headless Chromium against `midview serve`, beside the time of the API requests
the pages make (measured in the same run with httpx).

The job is made behind the API (a succeeded job with its stage runs and a cameras.geojson of N cameras in
the database and the storage of the served data folder): what is timed is the page, not a pipeline.

    python bench/dashboard.py [--images 200] [--runs 5] [--report runs/demo/report.html]
                              [--json docs/results/dashboard.json]

With --report, the static report a demo wrote is timed too (its job page and its map, opened from the
file).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

KEY = "mv_dashboardbenchkey0123456789abcdef"
STAGES = ["aerial_sfm", "train_splat", "plan_views", "render_views", "match_views", "reduce", "combined_sfm"]


def make_job(data_dir: Path, n: int) -> str:
    """A succeeded job of n images (n/4 ground) with its stage runs, POS rows and cameras.geojson."""
    import cv2
    import numpy as np

    from api.config import ApiSettings
    from shared.db import crud
    from shared.db.models import JobStatus, StageStatus
    from shared.db.session import make_engine, make_sessionmaker
    from shared.storage import get_storage
    from shared.storage.keys import image_key_for_name, job_key

    settings = ApiSettings(data_dir=data_dir)
    storage = get_storage(settings)
    engine = make_engine(settings.database_url)
    rng = np.random.default_rng(0)
    ok, jpg = cv2.imencode(".jpg", rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    names = [f"aerial/A{i:04d}.jpg" for i in range(n - n // 4)] + [
        f"ground/G{i:04d}.jpg" for i in range(n // 4)
    ]
    with make_sessionmaker(engine)() as s:
        tenant = crud.get_api_key(s, KEY, pepper=settings.api_key_pepper).tenant_id
        project = crud.create_project(s, tenant, f"bench-{uuid.uuid4().hex[:6]}")
        for name in names:
            key = image_key_for_name(tenant, project.id, name)
            storage.put_bytes(key, jpg.tobytes())
            crud.add_image(
                s,
                project.id,
                name,
                sha256="0" * 64,
                size_bytes=len(jpg),
                storage_key=key,
                width=64,
                height=48,
            )
        pos = [
            {"name": nm, "lat": 55.7 + 1e-5 * (i % 20), "lon": 13.19 + 1e-5 * (i // 20),
             "h": 60.0 if nm.startswith("aerial") else 2.0}
            for i, nm in enumerate(names)
        ]  # fmt: skip
        crud.add_pos_records(s, project.id, pos)
        job = crud.create_job(s, project.id, {"stages": STAGES})
        crud.set_job_status(s, job.id, JobStatus.running)
        for st in STAGES:
            crud.finish_stage(s, crud.start_stage(s, job.id, st), StageStatus.succeeded)
        feats = [{"type": "Feature",
                  "geometry": {"type": "Point", "coordinates": [p["lon"] + 2e-6, p["lat"], p["h"]]},
                  "properties": {"name": p["name"], "set": p["name"].split("/")[0], "registered": i % 7 != 3,
                                 "registered_by": "combined sfm", "position_std_m": 0.1, "to_pos_m": 0.14,
                                 "heading": 10.0, "pitch": -40.0, "roll": 0.5,
                                 "reason": "" if i % 7 != 3 else "no verified pair"}}
                 for i, p in enumerate(pos)]  # fmt: skip
        data = json.dumps({"type": "FeatureCollection", "features": feats}).encode()
        key = job_key(tenant, project.id, job.id, "combined", "gis/cameras.geojson")
        storage.put_bytes(key, data)
        crud.record_artifact(s, job.id, "gis", "combined/gis/cameras.geojson", key, len(data))
        sets = {"aerial": n - n // 4, "ground": n // 4}
        outcome = {
            "registered": sets,
            "images": sets,
            "result": "ok",
            "warnings": [],
            "from_stage": "combined_sfm",
        }
        crud.update_job_results(s, job.id, metrics={"outcome": outcome})
        crud.set_job_status(s, job.id, JobStatus.succeeded)
        s.commit()
        job_id = job.id
    engine.dispose()
    return job_id


def _chromium():
    """A headless Chromium (selenium) with the browser's console kept."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium")
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    quiet = ("--disable-background-networking", "--disable-component-update", "--disable-sync")
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--allow-file-access-from-files",
        "--window-size=1280,800",
        *quiet,
    ):
        opts.add_argument(arg)
    return webdriver.Chrome(options=opts, service=Service(shutil.which("chromedriver")))


def _time_pages(d, pages: dict[str, tuple[str, str]], runs: int) -> dict[str, list[float]]:
    """Seconds from navigation to each page (url, script true once it shows what it should), per run;
    the first round warms the browser's cache and is left out."""
    out: dict[str, list[float]] = {k: [] for k in pages}
    for _ in range(runs + 1):
        for name, (url, ready) in pages.items():
            d.get("about:blank")
            t0 = time.perf_counter()
            d.get(url)
            while not d.execute_script(ready):
                time.sleep(0.005)
                if time.perf_counter() - t0 > 30:
                    logs = [e["message"] for e in d.get_log("browser")][-5:]
                    raise RuntimeError(f"{name}: not shown after 30 s; the browser's console: {logs}")
            out[name].append(time.perf_counter() - t0)
    return {k: v[1:] for k, v in out.items()}


JOB_SHOWN = "return document.querySelectorAll('#stages tr.stage-row').length >= 7"
MAP_SHOWN = (  # the map drawn: its camera markers (Leaflet) and the table
    "return document.querySelectorAll('#map path.cam').length > 0"
    " && document.querySelectorAll('#ground-images tr.ground-row').length > 0"
)


def page_times(base: str, job_id: str, runs: int) -> dict[str, list[float]]:
    """Seconds from navigation to the page showing what it should, per page and run."""
    pages = {
        "job": (f"{base}/ui/#/jobs/{job_id}", JOB_SHOWN),
        "map": (f"{base}/ui/#/jobs/{job_id}/map", MAP_SHOWN),
        "ground": (f"{base}/ui/#/jobs/{job_id}/ground/G0000.jpg",
                   "const i = document.getElementById('ground-photo');"
                   "return !!(i && i.naturalWidth)"),
    }  # fmt: skip
    d = _chromium()
    try:
        d.get(f"{base}/ui/")
        d.execute_script(f"sessionStorage.setItem('midview-key', '{KEY}')")
        return _time_pages(d, pages, runs)
    finally:
        d.quit()


def report_times(report: Path, runs: int) -> dict[str, list[float]]:
    """Seconds from opening a static report (`midview demo`'s report.html: one file, its data inlined) to
    its job page (the outcome and the stage rows) and to its map (markers over the orthophoto)."""
    url = report.resolve().as_uri()
    d = _chromium()
    try:
        d.get(url)
        t0 = time.perf_counter()
        while not (job := d.execute_script("return location.hash")) and time.perf_counter() - t0 < 10:
            time.sleep(0.01)  # the report routes itself to its job
        pages = {"report": (url + job, JOB_SHOWN)}
        if job.startswith("#/jobs/"):
            pages["report_map"] = (url + job.rstrip("/") + "/map", MAP_SHOWN)
        return _time_pages(d, pages, runs)
    finally:
        d.quit()


def api_times(base: str, job_id: str, runs: int) -> list[float]:
    """Seconds of the map page's requests one after the other (job, project, artifacts, the layer, POS)."""
    import httpx

    h = {"Authorization": f"Bearer {KEY}"}
    times = []
    with httpx.Client(base_url=base, headers=h) as c:
        for _ in range(runs):
            t0 = time.perf_counter()
            job = c.get(f"/jobs/{job_id}").json()
            c.get(f"/projects/{job['project_id']}")
            arts = c.get(f"/jobs/{job_id}/artifacts").json()
            c.get(next(a["download_url"] for a in arts if a["name"].endswith("cameras.geojson")))
            c.get(f"/projects/{job['project_id']}/pos")
            times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=200)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--report", type=Path, help="a static report.html to time too (midview demo's)")
    args = ap.parse_args()
    import httpx
    from servers import free_ports

    tmp = Path(tempfile.mkdtemp(prefix="midview-bench-dashboard-"))
    (port,) = free_ports(1)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MIDVIEW_")}
    # what is timed is the pages, not the per-key rate limit (1200 a minute), which the rounds would reach
    env["MIDVIEW_RATE_LIMIT_PER_MINUTE"] = "0"
    exe = Path(sys.executable).with_name("midview")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", "cli.main"]
    log = open(tmp / "serve.log", "wb")
    args_serve = [*cmd, "serve", "--port", str(port), "--data-dir", str(tmp / "data"), "--api-key", KEY]
    proc = subprocess.Popen(args_serve, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(200):
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        job_id = make_job(tmp / "data", args.images)
        pages = page_times(base, job_id, args.runs)
        api = api_times(base, job_id, args.runs)
        if args.report:
            pages |= report_times(args.report, args.runs)
    finally:
        proc.terminate()
        proc.wait(15)
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)
    figures = {f"{k}_page_s_median": statistics.median(v) for k, v in pages.items()}
    figures |= {f"{k}_page_s_max": max(v) for k, v in pages.items()}
    figures["map_api_requests_s_median"] = statistics.median(api)
    figures["map_page_vs_its_requests"] = figures["map_page_s_median"] / figures["map_api_requests_s_median"]
    print(f"dashboard, a job of {args.images} images, {args.runs} runs ({os.cpu_count()} cores):")
    for k, v in figures.items():
        print(f"  {k}: {v:.3f}")
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        doc = {"command": "python " + " ".join(sys.argv), "commit": commit, "cores": os.cpu_count(),
               "images": args.images, "runs": args.runs, "report": str(args.report or ""),
               "figures": figures}  # fmt: skip
        args.json.write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
