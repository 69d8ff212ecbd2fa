"""The dashboard's page (api/ui) as one static, self-contained HTML file: `midview demo`'s report.

The page is the served dashboard's own code. Its API answers are recorded from the job folder into the
file (`window.MIDVIEW_SNAPSHOT`: JSON answers by path, and the images, layers and models the pages load as
data: URLs), shaped and checked by the API's own response schemas, so the report shows what the service
would: the job and its stages, the map, every ground image with its intermediate views and its matches
(coloured by verification, and on a synthetic survey by the ground truth), the 3D view (three.js inlined
through an import map), and the evaluation table of the demo. It opens from the file system, with no
server. Artifacts too large to embed are linked as files beside the report.

    path = write_report_page(out / "report.html", job, scene=out / "scene", evaluation={...})
"""

from __future__ import annotations

import base64
import json
import logging
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from api.matches import list_pairs, read_pair
from api.schemas import (
    ArtifactOut,
    JobDetail,
    JobOut,
    PairList,
    PairMatchesOut,
    PosOut,
    ProjectDetail,
    ProjectOut,
    StageRunOut,
)
from services import pipeline
from shared.outcome import job_outcome
from workers.execute import artifact_files
from workers.jobsync import content_type

logger = logging.getLogger("midview.report")

UI = Path(__file__).resolve().parents[1] / "api" / "ui"
THREE = UI / "node_modules" / "three"
LEAFLET = UI / "node_modules" / "leaflet" / "dist"
PROJECT_ID = "demo"
JOB_ID = "demo-job"
EMBED_MAX_BYTES = 8_000_000  # artifacts larger than this are linked, not embedded
IMAGE_MAX_WIDTH = 960  # images and views are embedded as JPEG at most this wide
JSON_KINDS = (".json", ".geojson", ".txt", ".las")


def _data_url(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode()}"


def jpeg_data_url(path: Path, max_width: int = IMAGE_MAX_WIDTH) -> str | None:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        return None
    if img.shape[1] > max_width:
        s = max_width / img.shape[1]
        img = cv2.resize(img, (max_width, max(1, round(img.shape[0] * s))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return _data_url(buf.tobytes(), "image/jpeg") if ok else None


def _now(path: Path) -> datetime:
    return datetime.fromtimestamp(path.stat().st_mtime, UTC) if path.exists() else datetime.now(UTC)


# -- the job's answers ---------------------------------------------------------------------------
def _stage_runs(job: pipeline.Job) -> tuple[list[StageRunOut], dict[str, Any], dict[str, float]]:
    """(stage runs, metrics: each stage's summary, timings) from the job folder's stage markers."""
    runs, metrics, timings = [], {}, {}
    for stage in job.options.stages:
        marker = pipeline.marker_path(job, stage)
        if not marker.is_file():
            continue
        doc = json.loads(marker.read_text())
        seconds = float(doc.get("seconds") or 0.0)
        end = _now(marker)
        runs.append(
            StageRunOut(
                stage=stage,
                status="succeeded",
                attempt=1,
                worker="midview demo",
                started_at=datetime.fromtimestamp(end.timestamp() - seconds, UTC),
                finished_at=end,
                duration_s=round(seconds, 3),
                error=None,
            )
        )
        metrics[stage] = doc.get("summary") or {}
        timings[stage] = round(seconds, 3)
    return runs, metrics, timings


def _pos_rows(job: pipeline.Job) -> list[dict]:
    from services.pos import read_pos

    names = [f"{s}/{p.name}" for s in ("aerial", "ground") for p in sorted((job.image_dir / s).iterdir())]
    rows = []
    for r in read_pos(job.pos, names):
        rows.append(
            PosOut(
                image_name=r.name,
                lat=r.lat,
                lon=r.lon,
                h=r.h,
                attitude=None if r.R_world_from_cam is None else np.asarray(r.R_world_from_cam).tolist(),
                std_xy=r.std_xy,
                std_z=r.std_z,
                std_att=r.std_att,
                source_format="csv",
            ).model_dump(mode="json")
        )
    return rows


class _Truth:
    """GT-correctness of matches on a synthetic survey (services.evaluation's test, per match)."""

    def __init__(self, scene: Path):
        from services.evaluation.common import DepthMaps, read_gt_model

        self.cams, self.poses = read_gt_model(scene)
        self.depths = DepthMaps(scene / "gt" / "depth.h5")

    def __call__(self, aerial: str, ground: str, xy_a: np.ndarray, xy_g: np.ndarray) -> list[bool] | None:
        from services.evaluation.matches import gt_correct_mask

        if aerial not in self.poses or ground not in self.poses or len(xy_a) == 0:
            return None
        ok = gt_correct_mask(
            xy_a,
            xy_g,
            self.cams[aerial],
            self.poses[aerial],
            self.depths[aerial],
            self.cams[ground],
            self.poses[ground],
            self.depths[ground],
        )
        return ok.astype(bool).tolist()

    def close(self) -> None:
        self.depths.close()


def _job_answers(job: pipeline.Job) -> dict[str, Any]:
    """The project's and the job's answers: /projects, /projects/P, its jobs and POS, /jobs/J."""
    created = _now(job.root / pipeline.JOB_FILE)
    runs, metrics, timings = _stage_runs(job)
    outcome = job_outcome(metrics)
    n_images = {s: sum(1 for _ in (job.image_dir / s).iterdir()) for s in ("aerial", "ground")}
    pos = _pos_rows(job)
    project = ProjectOut(
        id=PROJECT_ID,
        name=f"midview demo: {job.root.parent.name}",
        description="midview demo (a synthetic survey)",
        crs=None,
        origin_lat=None,
        origin_lon=None,
        origin_h=None,
        created_at=created,
    )
    total = max(len(job.options.stages), 1)
    done = len(runs) == len(job.options.stages)
    job_out = JobOut(
        id=JOB_ID,
        project_id=PROJECT_ID,
        status="succeeded" if done else "failed",
        current_stage=None,
        progress=1.0 if done else len(runs) / total,
        progress_percent=100.0 if done else round(100.0 * len(runs) / total, 1),
        options=job.options.model_dump(mode="json"),
        timings=timings,
        metrics={**metrics, "outcome": outcome},
        outcome=outcome,
        error=None if done else "the demo's job did not finish every stage",
        attempt=1,
        key=None,
        campaign_id=None,
        created_at=created,
        started_at=created,
        finished_at=max((r.finished_at for r in runs), default=created),
    )
    return {
        "/projects": [project.model_dump(mode="json")],
        f"/projects/{PROJECT_ID}": ProjectDetail(
            **project.model_dump(), images=n_images, pos_records=len(pos), jobs=1
        ).model_dump(mode="json"),
        f"/projects/{PROJECT_ID}/jobs": [job_out.model_dump(mode="json")],
        f"/projects/{PROJECT_ID}/pos": pos,
        f"/jobs/{JOB_ID}": JobDetail(**job_out.model_dump(), stages=runs).model_dump(mode="json"),
    }


def _artifacts(job: pipeline.Job, blobs: dict[str, str]) -> list[dict]:
    """The job's artifacts (ArtifactOut); the views (as JPEG) and the small layers go into `blobs`,
    the others are linked as files of the job folder beside the report."""
    arts = []
    for stage in job.options.stages:
        for rel, kind, path in artifact_files(job.root, stage):
            key = f"/report/artifacts/{rel}"
            size = path.stat().st_size
            url = None
            if kind == "orthophoto-image" and size <= EMBED_MAX_BYTES:  # the map's background, with its alpha
                url = _data_url(path.read_bytes(), "image/png")
            elif path.suffix == ".png" and rel.startswith("views/"):
                url = jpeg_data_url(path)
            elif path.suffix in JSON_KINDS and size <= EMBED_MAX_BYTES:
                url = _data_url(path.read_bytes(), content_type(path))
            if url:
                blobs[key] = url
            art = ArtifactOut(
                id=f"art-{len(arts)}",
                job_id=JOB_ID,
                kind=kind,
                name=rel,
                size_bytes=size,
                sha256=None,
                content_type=content_type(path),
                created_at=_now(path),
                download_url=key if url else f"{job.root.name}/{rel}",
            )
            arts.append(art.model_dump(mode="json"))
    return arts


def _pair_answers(job: pipeline.Job, scene: Path | None) -> dict[str, Any]:
    """/jobs/J/pairs and each pair's matches, with their truth on a synthetic survey (`scene`)."""
    matches = job.transfer.matches
    if not matches.is_file():
        return {}
    method, pairs = list_pairs(matches)
    out = {
        f"/jobs/{JOB_ID}/pairs": PairList(
            artifact="transfer/matches.h5", method=method, total=len(pairs), pairs=pairs
        ).model_dump(mode="json")
    }
    truth = _Truth(scene) if scene is not None and (scene / "gt" / "depth.h5").is_file() else None
    try:
        for p in pairs:
            d = read_pair(matches, p["aerial"], p["ground"])
            answer = PairMatchesOut(artifact="transfer/matches.h5", **d).model_dump(mode="json")
            if truth is not None:
                xy_a, xy_g = np.asarray(d["aerial_xy"]), np.asarray(d["ground_xy"])
                answer["truth"] = truth(p["aerial"], p["ground"], xy_a, xy_g)
            a, g = p["aerial"].split("/", 1)[1], p["ground"].split("/", 1)[1]
            out[f"/jobs/{JOB_ID}/pairs/aerial/{a}/ground/{g}"] = answer
    finally:
        if truth is not None:
            truth.close()
    return out


def snapshot(job: pipeline.Job, scene: Path | None = None, evaluation: dict | None = None) -> dict:
    """The recorded API answers of one finished job: {"start": the page's route, "json": {path:
    answer}, "blobs": {path: data URL}, "evaluation"}."""
    blobs: dict[str, str] = {}
    jsons = _job_answers(job)
    jsons[f"/jobs/{JOB_ID}/artifacts"] = _artifacts(job, blobs)
    for s in ("aerial", "ground"):  # the images, as the ground pages and the match drawings load them
        for p in sorted((job.image_dir / s).iterdir()):
            url = jpeg_data_url(p)
            if url:
                blobs[f"/projects/{PROJECT_ID}/images/{s}/{p.name}/download"] = url
    jsons.update(_pair_answers(job, scene))
    return {"start": f"#/jobs/{JOB_ID}", "json": jsons, "blobs": blobs, "evaluation": evaluation}


# -- the page ------------------------------------------------------------------------------------
def _module_url(path: Path, replace: dict[str, str] | None = None) -> str:
    code = path.read_text()
    for a, b in (replace or {}).items():
        code = code.replace(a, b)
    return _data_url(code.encode(), "text/javascript")


def import_map() -> dict[str, str]:
    """three.js, its orbit controls and the 3D view as data: modules (file:// pages cannot load modules
    from files); empty where three.js is not installed (the page then says so)."""
    core, module = THREE / "build" / "three.core.min.js", THREE / "build" / "three.module.min.js"
    controls = THREE / "examples" / "jsm" / "controls" / "OrbitControls.js"
    if not (core.is_file() and module.is_file() and controls.is_file()):
        logger.warning("three.js is not installed (scripts/setup.sh): the report has no 3D view")
        return {}
    return {
        "three-core": _module_url(core),
        "three": _module_url(module, {"./three.core.min.js": "three-core"}),
        "three/addons/controls/OrbitControls.js": _module_url(controls),
        "midview/view3d": _module_url(UI / "view3d.js"),
    }


def leaflet_inline() -> tuple[str, str]:
    """(css, script) of Leaflet for the page itself, its css images as data: URLs; empty where Leaflet is
    not installed (the map then says so)."""
    css, js = LEAFLET / "leaflet.css", LEAFLET / "leaflet.js"
    if not (css.is_file() and js.is_file()):
        logger.warning("Leaflet is not installed (scripts/setup.sh): the report has no map")
        return "", ""

    def image(m: re.Match) -> str:
        f = LEAFLET / m.group(1)
        return f"url({_data_url(f.read_bytes(), 'image/png')})" if f.is_file() else m.group(0)

    style = re.sub(r"url\((images/[^)]+\.png)\)", image, css.read_text())
    return style, js.read_text().replace("</script", "<\\/script")


def _script_json(obj: Any) -> str:
    """JSON safe inside a <script> element."""
    return json.dumps(obj, separators=(",", ":")).replace("</", "<\\/").replace("<!--", "<\\!--")


def write_report_page(
    path: str | Path, job: pipeline.Job, scene: Path | None = None, evaluation: dict | None = None
) -> Path:
    """Write the static dashboard of `job` to `path` (artifact links relative to the job folder's
    parent, which should be the report's folder). Returns the path."""
    path = Path(path)
    snap = snapshot(job, scene, evaluation)
    page = (UI / "index.html").read_text()
    css = (UI / "app.css").read_text()
    app = (UI / "app.js").read_text()
    page = page.replace('<link rel="stylesheet" href="app.css">', f"<style>\n{css}\n</style>")
    leaflet_css, leaflet_js = leaflet_inline()
    leaflet_link = '<link rel="stylesheet" href="node_modules/leaflet/dist/leaflet.css">'
    page = page.replace(leaflet_link, f"<style>\n{leaflet_css}\n</style>")
    page = page.replace(
        '<script src="node_modules/leaflet/dist/leaflet.js"></script>', f"<script>\n{leaflet_js}\n</script>"
    )
    page = re.sub(
        r'<script type="importmap">.*?</script>',
        lambda _: f'<script type="importmap">{_script_json({"imports": import_map()})}</script>',
        page,
        flags=re.S,
    )
    app = app.replace("</script", "<\\/script")
    page = page.replace(
        '<script type="module" src="app.js"></script>',
        f'<script id="midview-snapshot" type="application/json">{_script_json(snap)}</script>\n'
        f'<script type="module">\n{app}\n</script>',
    )
    page = page.replace("<title>midview</title>", "<title>midview report</title>")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page)
    logger.info("report page: %s (%.1f MB)", path, path.stat().st_size / 1e6)
    return path
