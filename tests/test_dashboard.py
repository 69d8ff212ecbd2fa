"""The web dashboard in a real browser: headless Chromium (Debian's package) driven by Selenium against
`midview serve` (SQLite, local storage, the embedded worker) in its own process, run from a plain
install of the package (its wheel, installed apart from the checkout, as `pip install` and the Docker
image have it). Signs in, creates a project, uploads a survey through the page's file inputs (the API's
multipart uploads), checks the POS, starts a job and watches it to the end through the event stream,
opens the map and a ground image's page, and checks what they show; then the same pages 390 px wide.
Screenshots go to runs/test-artifacts/dashboard/ (or MIDVIEW_TEST_ARTIFACTS); the browser console must
stay free of errors.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.pipeline import DEFAULT_STAGES

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
KEY = "mv_dashboardtestkey0123456789abcdef"
OPTIONS = {"sfm_features": "sift", "matcher": "aliked-lightglue", "view_planner": "both",
           "views_per_ground_image": 1, "splat_steps": 1000, "splat_max_width": 240, "max_keypoints": 1024,
           "seed": 0}  # fmt: skip
JOB_TIMEOUT_S = 600
ORTHO_LOADED = "const i = document.querySelector('#map img.orthophoto'); return i && i.naturalWidth"
TOGGLE_LAYER = (  # a layer of the map's layer control, by its label
    "for (const l of document.querySelectorAll('#map .leaflet-control-layers label'))"
    " if (l.textContent.trim() === arguments[0]) l.querySelector('input').click()"
)
# the cells' texts of the rows a selector finds, read at once
ROWS = (
    "return [...document.querySelectorAll(arguments[0])].map((r) => [...r.cells].map((c) => c.textContent))"
)
SERVE: dict[str, Path] = {}  # the server's data folder (its embedded worker's job folders)


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    """`tiny`: 20 aerial, 4 ground images."""
    from services import synth

    return synth.main(synth.confs["tiny"], tmp_path_factory.mktemp("survey") / "tiny", seed=0)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`midview serve` from a plain install of the package (its wheel, installed apart from the checkout:
    the page's three.js and Leaflet come from the package, no npm at test time) on a free port with a
    known API key; its base URL."""
    from servers import _stop, install_wheel, start_midview_serve

    folder = tmp_path_factory.mktemp("serve")
    site = install_wheel(folder / "install")
    SERVE["data"] = folder / "data"
    env = {"OMP_NUM_THREADS": "1", "MIDVIEW_EVENTS_POLL_S": "0.2"}
    modules = "import api, cli, services, shared, workers as w; print(api.__file__, w.__file__)"
    where = subprocess.run(  # the server's own modules: the installed ones, not the checkout's
        [sys.executable, "-c", modules],
        cwd=site.parent, env={**os.environ, "PYTHONPATH": str(site)}, capture_output=True, text=True,
    )  # fmt: skip
    assert where.returncode == 0 and all(Path(f).is_relative_to(site) for f in where.stdout.split()), where
    assert (site / "api" / "ui" / "node_modules" / "three" / "build" / "three.module.js").is_file()
    proc, base = start_midview_serve(folder / "data", KEY, folder / "serve.log", env, site=site)
    try:
        yield base
    finally:
        _stop(proc, timeout=15)


@pytest.fixture(scope="module")
def browser():
    if not (CHROMIUM and DRIVER):
        pytest.skip("needs Debian's chromium and chromium-driver (scripts/test.sh installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    quiet = ("--disable-background-networking", "--disable-component-update", "--disable-sync")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1280,800", *quiet,
                "--no-first-run", "--enable-unsafe-swiftshader"):  # fmt: skip
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(DRIVER))
    driver.set_window_size(1280, 800)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def shots() -> Path:
    folder = Path(os.environ.get("MIDVIEW_TEST_ARTIFACTS", ROOT / "runs" / "test-artifacts")) / "dashboard"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _wait(driver, check, timeout=30.0, what="condition"):
    """check(driver) until truthy; its value."""
    from selenium.common.exceptions import StaleElementReferenceException, WebDriverException

    deadline = time.monotonic() + timeout
    while True:
        try:
            value = check(driver)
            if value:
                return value
        except (StaleElementReferenceException, WebDriverException):
            pass
        if time.monotonic() > deadline:
            raise AssertionError(
                f"timed out waiting for {what}: {driver.current_url}\n{_text(driver)[:3000]}"
            )
        time.sleep(0.2)


def urlopen_json(server: str, driver) -> str:
    """The combined report of the job on the page, read through the API with the test's key."""
    import httpx

    job_id = driver.current_url.split("#/jobs/")[1].split("/")[0]
    headers = {"Authorization": f"Bearer {KEY}"}
    arts = httpx.get(f"{server}/jobs/{job_id}/artifacts", headers=headers).json()
    url = next(a["download_url"] for a in arts if a["name"] == "combined/report.json")
    return httpx.get(url, headers=headers).text


def _text(driver) -> str:
    return driver.find_element("tag name", "main").text


def _by(driver, css):
    return driver.find_element("css selector", css)


def _all(driver, css):
    return driver.find_elements("css selector", css)


def _console_errors(driver, expected=()) -> list:
    """Severe browser log entries but failed requests the test made on purpose ((url part, status))."""
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    return [e for e in errors if not (e["source"] == "network" and any(
        url in e["message"] and code in e["message"] for url, code in expected))]  # fmt: skip


def test_sign_in_upload_run_and_inspect_a_survey(server, browser, survey, shots):
    import httpx

    d = browser
    d.get(f"{server}/ui/")
    _wait(d, lambda d: _by(d, "#api-key"), what="the sign-in form")
    _by(d, "#api-key").send_keys("mv_wrong")
    _by(d, "#signin button").click()
    _wait(d, lambda d: "sign in failed" in _by(d, "#signin-error").text, what="the refusal of a wrong key")
    _by(d, "#api-key").clear()
    _by(d, "#api-key").send_keys(KEY)
    _by(d, "#signin button").click()
    _wait(d, lambda d: _by(d, "#projects"), what="the projects list")

    _by(d, "#project-name").send_keys("tiny through the browser")
    _by(d, "#create-project button").click()
    _wait(d, lambda d: "#/projects/" in d.current_url and _by(d, "#aerial-files"), what="the project page")
    images = survey / "images"
    aerial, ground = sorted((images / "aerial").iterdir()), sorted((images / "ground").iterdir())
    _by(d, "#aerial-files").send_keys("\n".join(str(p) for p in aerial))
    _by(d, "#ground-files").send_keys("\n".join(str(p) for p in ground))
    _wait(d, lambda d: _by(d, "#aerial-total-text").text.startswith("20/20 files"), 120, "the aerial uploads")
    _wait(d, lambda d: _by(d, "#ground-total-text").text.startswith("4/4 files"), 60, "the ground uploads")
    rows = _all(d, "#aerial-uploads tr.upload-row")
    assert len(rows) == 20 and all(r.find_elements("css selector", "td")[-1].text == "uploaded" for r in rows)
    assert float(_by(d, "#aerial-total").get_attribute("value")) == 1.0
    # a POS file naming an image that is not there: refused, with the row's message
    bad = survey.parent / "bad-pos.csv"
    text = (survey / "pos.csv").read_text()
    last = text.strip().splitlines()[-1]
    bad.write_text(text + "aerial/NOPE.jpg," + last.split(",", 1)[1] + "\n")
    _by(d, "#pos-file").send_keys(str(bad))
    _wait(d, lambda d: "NOPE.jpg" in _by(d, "#pos-result").text, what="the POS check's message")
    _by(d, "#pos-file").send_keys(str(survey / "pos.csv"))
    _wait(d, lambda d: "24 rows stored" in _by(d, "#pos-result").text, what="the POS upload")
    _by(d, "#cameras-file").send_keys(str(survey / "cameras.json"))
    _wait(d, lambda d: "cameras.json stored" in _by(d, "#toast").text, what="the intrinsics")
    _wait(d, lambda d: "20 aerial, 4 ground images, 24 POS rows" in _by(d, "#image-counts").text)
    d.save_screenshot(str(shots / "project-1280.png"))

    # the options form, generated from GET /options: a profile (the workers' preselected), every option
    # with its profile's default shown, and the fields a 422 names outlined
    from selenium.webdriver.support.ui import Select

    assert Select(_by(d, "#opt-profile")).first_selected_option.get_attribute("value") == "cpu"
    # the cpu profile's estimated time for this project's images (GET /options' cost model)
    estimate = "for 20 aerial and 4 ground images on 2 CPU cores"
    _wait(d, lambda d: estimate in _by(d, "#opt-estimate").text, 30, "the time estimate")
    assert re.match(r"about \d+ min ", _by(d, "#opt-estimate").text), _by(d, "#opt-estimate").text
    assert _by(d, "#opt-splat-steps").get_attribute("placeholder") == "3000"
    Select(_by(d, "#opt-profile")).select_by_value("gpu")
    assert _by(d, "#opt-splat-steps").get_attribute("placeholder") == "7000"
    Select(_by(d, "#opt-profile")).select_by_value("cpu")
    d.execute_script("document.querySelectorAll('#job-form details').forEach((e) => { e.open = true; })")
    _by(d, "#opt-views-per-ground-image").send_keys("0")
    _by(d, "#start-job").click()
    _wait(d, lambda d: "views_per_ground_image" in _by(d, "#toast").text, what="the option's error")
    assert "bad-field" in _by(d, "#opt-views-per-ground-image").get_attribute("class")
    for name, value in OPTIONS.items():
        field = _by(d, "#opt-" + name.replace("_", "-"))
        if field.tag_name == "select":
            Select(field).select_by_value(str(value))
        else:
            field.clear()
            field.send_keys(str(value))
    _by(d, "#start-job").click()
    _wait(d, lambda d: "#/jobs/" in d.current_url and _by(d, "#job-status"), what="the job page")
    job_url = d.current_url
    seen = set()

    labels = set()

    def finished(d):
        status = _by(d, "#job-status").text
        seen.add(status)
        labels.update(
            r[1] for r in d.execute_script(ROWS, "#stages tr.stage-row") if r[1].startswith("running")
        )
        return status in ("succeeded", "failed", "cancelled") and status

    assert _wait(d, finished, JOB_TIMEOUT_S, "the end of the job") == "succeeded", _text(d)
    assert "running" in seen  # the page followed the job live
    # the running stage shows its share done
    assert labels and all(re.fullmatch(r"running \d{1,3}%", x) for x in labels), labels
    # (read in one script: the page re-renders its rows as the last events arrive)
    stages = d.execute_script(ROWS, "#stages tr.stage-row")
    assert [r[0] for r in stages] == list(DEFAULT_STAGES) and all(r[1] == "succeeded" for r in stages), stages
    assert float(_by(d, "#job-progress").get_attribute("value")) == 100.0
    # the stream's `end` event is logged after the last progress event's re-render: wait for it
    log = _wait(
        d, lambda d: (t := _by(d, "#job-log").text) and "end: succeeded" in t and t, 30, "the end event"
    )
    assert "train_splat" in log and "end: succeeded" in log
    # the stages' progress reports, as the events carry them: a stage and its message
    assert re.search(r" (train_splat|render_views|match_views): \S", log), log
    assert "ground" in _by(d, "#job-outcome").text
    # the outcome first: N of M ground images registered, why the others were left out, and an amber
    # "finished with warnings" where images stayed out
    shown = d.current_url.split("#/jobs/")[1].split("/")[0]
    outcome = httpx.get(f"{server}/jobs/{shown}", headers={"Authorization": f"Bearer {KEY}"}).json()[
        "outcome"
    ]
    registered = outcome["registered"].get("ground", 0)
    assert _by(d, "#job-headline").text.startswith(f"{registered} of 4 ground images registered")
    left_out = sum(outcome["causes"].values())
    assert left_out == 4 - registered and (left_out == 0 or "left out" in _by(d, "#job-headline").text)
    assert _by(d, "#job-result").text == ("finished with warnings" if registered < 4 else "")
    # the ground images as thumbnails: registered first, the others grouped by their cause
    _wait(d, lambda d: len(_all(d, "#ground-grid a.thumb")) == 4, 30, "the ground images' grid")
    assert len(_all(d, "#ground-grid a.thumb.ok")) == registered
    groups = [g.get_attribute("data-group") for g in _all(d, "#ground-grid .thumb-group")]
    assert set(groups) - {"registered"} == set(outcome["causes"]) and groups[0] == (
        "registered" if registered else groups[0]
    )
    _wait(d, lambda d: len(_all(d, "#artifacts tr.artifact-row")) >= 10, what="the artifacts")
    # the named products, one zip each, above the list of files
    assert _all(d, "#bundle-gis") and _all(d, "#bundle-colmap")
    assert not _by(d, "#rerun-force").is_selected()  # a rerun skips what is up to date unless forced
    import io
    import zipfile

    z = httpx.get(f"{server}/jobs/{shown}/bundles/gis.zip", headers={"Authorization": f"Bearer {KEY}"})
    assert "combined/gis/cameras.gpkg" in zipfile.ZipFile(io.BytesIO(z.content)).namelist()
    names = [r[0] for r in d.execute_script(ROWS, "#artifacts tr.artifact-row")]
    assert "combined/gis/cameras.gpkg" in names and "combined/report.json" in names
    d.save_screenshot(str(shots / "job-1280.png"))

    _by(d, "#map-link").click()
    _wait(d, lambda d: _all(d, "#map path.cam"), 30, "the map")  # Leaflet, vector layers in SVG
    assert len(_all(d, "#map path.cam.aerial")) >= 16
    assert len(_all(d, "#map path.pos")) == 24  # every image's POS
    # the background: the survey's orthophoto, loaded; the aerial footprints one click away
    _wait(d, lambda d: d.execute_script(ORTHO_LOADED), 30, "the orthophoto")
    assert not _all(d, "#map path.footprint")
    d.execute_script(TOGGLE_LAYER, "aerial footprints")
    assert len(_all(d, "#map path.footprint")) == 20
    ground_rows = _all(d, "#ground-images tr.ground-row")
    assert len(ground_rows) == 4
    for r in ground_rows:
        cells = [c.text for c in r.find_elements("css selector", "td")]
        assert cells[1] in ("yes", "no") and (cells[1] == "yes" or cells[4])  # not registered: the reason
    registered = sum(r.find_elements("css selector", "td")[1].text == "yes" for r in ground_rows)
    assert (
        len(_all(d, "#map path.cam.ground")) == 4 and len(_all(d, "#map path.error-line")) >= 16 + registered
    )
    d.save_screenshot(str(shots / "map-1280.png"))

    # the 3D view: every point of the combined model and every registered camera (three.js, WebGL)
    _by(d, "#view3d-link").click()
    drawn = _wait(d, lambda d: d.execute_script("return window.midview3d"), 60, "the 3D view")
    report = json.loads(urlopen_json(server, d))
    assert drawn["points"] == report["num_points3D"] > 0
    assert drawn["cameras"] == sum(report["num_registered"].values())
    assert drawn.get("webgl", True), "no WebGL in this Chromium"
    splat = _wait(d, lambda d: d.execute_script("return window.midview3dSplat"), 60, "the 3DGS view")
    job_id = d.current_url.split("#/jobs/")[1].split("/")[0]
    metrics = httpx.get(f"{server}/jobs/{job_id}", headers={"Authorization": f"Bearer {KEY}"}).json()[
        "metrics"
    ]
    assert splat["total"] == metrics["train_splat"]["num_gaussians"] and 0 < splat["points"] <= splat["total"]
    d.save_screenshot(str(shots / "3d-1280.png"))

    # a click on a camera picks it (the camera under the pointer), on a ground camera opens its page
    def click_camera(name: str) -> None:  # a pointer pressed and released where the camera is drawn
        d.execute_script(
            "const c = document.querySelector('#view3d canvas'), r = c.getBoundingClientRect();"
            "const [x, y] = window.midview3dScreenOf(arguments[0]);"
            "for (const type of ['pointerdown', 'pointerup']) c.dispatchEvent(new PointerEvent(type,"
            " {clientX: r.left + x, clientY: r.top + y, bubbles: true, pointerId: 1, isPrimary: true}))",
            name,
        )

    aerial_cam = next(n for n in drawn["names"] if n.startswith("aerial/"))
    click_camera(aerial_cam)
    debug = d.execute_script(
        "const c = document.querySelector('#view3d canvas'), r = c.getBoundingClientRect();"
        "return [window.midview3dScreenOf(arguments[0]), r.width, r.height, c.width, c.height]",
        aerial_cam,
    )
    assert d.execute_script("return window.midview3dPicked") == aerial_cam, debug
    assert "/3d" in d.current_url
    ground_cams = [n for n, r in report["ground"].items() if r["registered"]]
    if ground_cams:
        click_camera(ground_cams[0])
        opened = "a ground page from the 3D view"
        _wait(d, lambda d: "/ground/" in d.current_url and _all(d, "#ground-photo"), 30, opened)
        d.back()
        _wait(d, lambda d: d.execute_script("return window.midview3d"), 60, "the 3D view again")
    d.back()
    _wait(d, lambda d: _all(d, "#ground-images tr.ground-row"), 30, "the map again")
    # a ground camera's marker opens its page
    marker = _all(d, "#map path.cam.ground")[0]
    d.execute_script("arguments[0].dispatchEvent(new MouseEvent('click', {bubbles: true}))", marker)
    opened = "a ground page from the map"
    _wait(d, lambda d: "/ground/" in d.current_url and _all(d, "#ground-photo"), 30, opened)
    d.back()
    _wait(d, lambda d: _all(d, "#ground-images tr.ground-row"), 30, "the map again")
    ground_rows = _all(d, "#ground-images tr.ground-row")
    ground_rows[0].find_element("css selector", "a").click()
    photo_width = "const i = document.getElementById('ground-photo'); return i && i.naturalWidth"
    _wait(d, lambda d: d.execute_script(photo_width), 30, "the ground image")
    assert d.execute_script("return document.getElementById('ground-photo').naturalWidth") == 320
    # its intermediate views (the ground-aware planner renders one per ground image here), loaded
    views_loaded = "return [...document.querySelectorAll('#views img.view-image')].map((i) => i.naturalWidth)"
    widths = _wait(d, lambda d: (w := d.execute_script(views_loaded)) and all(w) and w, 30, "the views")
    assert len(widths) >= 1 and all(w >= 320 for w in widths)  # ground-aware at 320, the paper's wider
    # every view planned for it is listed: the ground-aware one (its source) and the paper planner's
    # (which list it among their ground images)
    auth = {"Authorization": f"Bearer {KEY}"}
    arts = {a["name"]: a for a in httpx.get(f"{server}/jobs/{job_id}/artifacts", headers=auth).json()}
    plan_url = arts["views/views.json"]["download_url"]
    plan = httpx.get(plan_url if plan_url.startswith("http") else server + plan_url, headers=auth).json()
    name = _by(d, "h1").text
    mine = [v for v in plan["views"] if v["source"] == name or name in v.get("ground", [])]
    assert len(widths) == sum(f"views/{v['name']}.png" in arts for v in mine), (name, len(widths), mine)
    assert {v["planner"] for v in mine} == {"paper", "ground-aware"}, mine
    if _by(d, "#pose-registered").text == "no":
        assert _by(d, "#pose-reason").text
    pairs = _all(d, "#pairs tr.pair-row")
    if pairs:  # the first pair is drawn: both images side by side with its matches
        _wait(d, lambda d: d.execute_script("return document.getElementById('pair-canvas').width") > 320,
              30, "the match picture")  # fmt: skip
        assert "matches" in _by(d, "#pair-info").text
    d.save_screenshot(str(shots / "ground-1280.png"))

    # a shared link survives the sign-in: signed out, the job's link asks for the key, then opens the job
    _by(d, "#signout").click()
    d.get(job_url)
    _wait(d, lambda d: _all(d, "#api-key"), 30, "the sign-in form")
    _by(d, "#api-key").send_keys(KEY)
    _by(d, "#signin button").click()
    _wait(d, lambda d: _all(d, "#stages tr.stage-row"), 30, "the shared job's page")
    assert d.current_url == job_url
    # reopened, a finished job shows its log as the server keeps it: every stage run, in order, with what
    # the stage reported while it ran
    log = _wait(d, lambda d: (t := _by(d, "#job-log").text) and "== combined_sfm" in t and t, 30, "the log")
    assert "== aerial_sfm (attempt 1, succeeded" in log and "== combined_sfm (attempt 1, succeeded" in log, (
        log
    )
    assert log.index("== aerial_sfm") < log.index(" aerial_sfm 100%") < log.index("== train_splat")

    # a phone: 390 px wide, nothing wider than the screen
    d.set_window_size(390, 844)
    for url, shot, ready in [(job_url, "job-390.png", "#stages tr.stage-row"),
                             (job_url + "/map", "map-390.png", "#map path.cam")]:  # fmt: skip
        d.get(url)
        _wait(d, lambda d, css=ready: _all(d, css), 30, shot)
        width = d.execute_script("return document.documentElement.scrollWidth")
        inner = d.execute_script("return window.innerWidth")
        assert width <= inner + 1, (shot, width, inner)
        d.save_screenshot(str(shots / shot))
    # no script error, and no failed request but those the test made on purpose (the wrong key's 401 on
    # /projects, the bad POS file's 422, the job with an option out of its range)
    unexpected = _console_errors(d, [("/projects -", "401"), ("/pos -", "422"), ("/jobs -", "422")])
    assert unexpected == [], unexpected


def test_the_demo_report_is_the_same_page_static_from_the_file_system(browser, survey, shots, tmp_path):
    """`midview demo`'s report.html (cli/report_page.py) of the job the test above ran: one file that opens
    from the file system with no server, the dashboard's own pages on the recorded answers, matches
    coloured by the ground truth of the synthetic survey."""
    from cli.report_page import snapshot, write_report_page
    from services import pipeline
    from services.evaluation import evaluate_matches
    from services.evaluation.common import read_covisible

    roots = sorted(p.parent for p in (SERVE["data"] / "work").glob("*/job.json"))
    assert len(roots) == 1, f"the job of the test above: {roots}"
    job = pipeline.Job.load(roots[0])
    evaluation = {"title": "methods", "columns": ["method", "GT-correct"], "rows": [["midview", "1.0"]],
                  "notes": ["a note"], "pictures": []}  # fmt: skip
    snap = snapshot(job, survey, evaluation)
    # the truth of each match is the evaluator's: over the co-visible pairs, verified and true = GT-correct
    covisible = {(a, g) for a, g, _ in read_covisible(survey / "gt" / "covisible.csv")}
    pairs = {k: v for k, v in snap["json"].items() if "/pairs/aerial/" in k}
    assert pairs and all(len(v["truth"]) == v["num_matches"] for v in pairs.values())
    true_verified = sum(
        sum(t and i for t, i in zip(v["truth"], v["inliers"], strict=True))
        for v in pairs.values()
        if (v["aerial"], v["ground"]) in covisible
    )
    ev = evaluate_matches(survey, job.dir("transfer") / "matches.h5")
    assert true_verified == ev["total_gt_correct"]
    # one file: no request leaves it (the large 3DGS model is linked beside it, not loaded)
    out = tmp_path / "report"
    out.mkdir()
    (out / job.root.name).symlink_to(job.root)
    path = write_report_page(out / "report.html", job, survey, evaluation)
    d = browser
    d.set_window_size(1280, 800)
    d.get_log("browser")  # drop what the test above left
    d.get(path.as_uri())
    _wait(d, lambda d: _all(d, "#stages tr.stage-row"), 30, "the report's job page")
    stages = d.execute_script(ROWS, "#stages tr.stage-row")
    assert [r[0] for r in stages] == list(DEFAULT_STAGES) and all(r[1] == "succeeded" for r in stages), stages
    # the outcome first; the evaluation against the ground truth is a tab of its own
    assert not _all(d, "#evaluation-table")
    _by(d, "#evaluation-link").click()
    _wait(d, lambda d: _all(d, "#evaluation-table"), 30, "the evaluation tab")
    assert d.execute_script(ROWS, "#evaluation-table tr.evaluation-row") == [["midview", "1.0"]]
    d.back()
    _wait(d, lambda d: _all(d, "#stages tr.stage-row"), 30, "the report's job page again")
    assert not _all(d, "#cancel-job") and not _all(d, "#rerun-job")  # read only
    names = [r[0] for r in d.execute_script(ROWS, "#artifacts tr.artifact-row")]
    assert "combined/report.json" in names and "splat/point_cloud.ply" in names
    report = json.loads((job.dir("combined") / "report.json").read_text())
    assert _by(d, "#job-outcome").text.startswith(f"ground {report['num_registered']['ground']}/4")
    assert _by(d, "#job-headline").text.startswith(f"{report['num_registered']['ground']} of 4 ground images")
    d.save_screenshot(str(shots / "report-job-1280.png"))
    _by(d, "#map-link").click()
    _wait(d, lambda d: _all(d, "#map path.cam"), 30, "the report's map")
    assert len(_all(d, "#map path.pos")) == 24
    _wait(d, lambda d: d.execute_script(ORTHO_LOADED), 30, "the report's orthophoto")
    _by(d, "#view3d-link").click()
    drawn = _wait(d, lambda d: d.execute_script("return window.midview3d"), 60, "the report's 3D view")
    assert drawn["points"] == report["num_points3D"] > 0
    assert drawn["cameras"] == sum(report["num_registered"].values())
    assert "point_cloud.ply" in _wait(d, lambda d: _by(d, "#splat3d-info").text, 30, "the 3DGS link")
    d.save_screenshot(str(shots / "report-3d-1280.png"))
    # the ground image with the most transferred matches: its views and its matches, by the truth
    best = max(pairs.values(), key=lambda v: (sum(v["truth"]), v["num_matches"]))
    d.get(f"{path.as_uri()}#/jobs/demo-job/ground/{best['ground'].split('/')[1]}")
    photo = "const i = document.getElementById('ground-photo'); return i && i.naturalWidth"
    _wait(d, lambda d: d.execute_script(photo), 30, "the photo")
    assert len(_all(d, "#views img.view-image")) >= 1
    rows = _all(d, "#pairs tr.pair-row")
    mine = [v for v in pairs.values() if v["ground"] == best["ground"]]
    mine.sort(key=lambda v: -(v["num_inliers"] if v["num_inliers"] is not None else v["num_matches"]))
    assert len(rows) == len(mine)
    green = "return document.getElementById('pair-canvas').dataset.green"
    first = mine[0]
    _wait(d, lambda d: d.execute_script(green) is not None, 30, "the match picture")
    assert _by(d, "#colour-by").is_displayed() and _by(d, "#colour-by").get_attribute("value") == "truth"
    assert int(d.execute_script(green)) == sum(first["truth"])
    assert "correct under the ground truth" in _by(d, "#pair-info").text
    d.save_screenshot(str(shots / "report-ground-1280.png"))
    # by verification: green are the verified matches
    d.execute_script("const s = document.getElementById('colour-by'); s.value = 'verification';"
                     "s.dispatchEvent(new Event('change'));")  # fmt: skip
    want = sum(first["inliers"]) if first["inliers"] is not None else 0
    _wait(d, lambda d: int(d.execute_script(green)) == want, 30, "the verification colours")
    d.set_window_size(390, 844)
    d.get(path.as_uri() + "#/jobs/demo-job/evaluation")
    _wait(d, lambda d: _all(d, "#evaluation-table"), 30, "the report's evaluation on a phone")
    assert (
        d.execute_script("return document.documentElement.scrollWidth")
        <= d.execute_script("return window.innerWidth") + 1
    )
    d.save_screenshot(str(shots / "report-job-390.png"))
    d.set_window_size(1280, 800)
    assert _console_errors(d) == []
