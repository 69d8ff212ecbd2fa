"""Job outputs through the API: the progress event stream, artifact downloads, and the pairs of a match
file. A test thread plays the worker by updating the job row through shared.db.crud."""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
import uuid
from pathlib import Path

import httpx
import numpy as np

from shared.db import crud
from shared.db.models import JobStatus
from shared.matchfile import MatchFile, PairMatches
from shared.storage.keys import job_key


def _job(env, tenant, make_jpeg) -> tuple[str, str]:
    """(project id, job id) of a new queued job (three aerial images, one ground image, POS, cameras)."""
    from conftest import jobbable_project

    c = env.client
    pid = jobbable_project(c, tenant.headers, make_jpeg)
    r = c.post(f"/projects/{pid}/jobs", json={}, headers=tenant.headers)
    assert r.status_code == 201
    return pid, r.json()["id"]


def _read_events(lines) -> list[tuple[str, dict]]:
    events, name, data = [], None, None
    for line in lines:
        if line.startswith("event: "):
            name = line[7:]
        elif line.startswith("data: "):
            data = json.loads(line[6:])
        elif line == "" and name is not None:
            events.append((name, data))
            name = data = None
    return events


def test_event_stream_follows_the_job_to_its_end(api_env, make_jpeg) -> None:
    t = api_env.tenant()
    _, jid = _job(api_env, t, make_jpeg)
    steps = [(0.1, "aerial_sfm"), (0.5, "train_splat"), (0.9, "reduce")]
    # The test thread plays the worker; it makes its next change only once the stream has reported the
    # previous state, so the test does not depend on how fast the stream polls on a loaded machine.
    reported = threading.Semaphore(0)

    def worker() -> None:
        for progress, stage in steps:
            assert reported.acquire(timeout=10)
            with api_env.session() as s:
                crud.update_job_progress(s, jid, progress, stage)
                s.commit()
        assert reported.acquire(timeout=10)
        with api_env.session() as s:
            crud.update_job_results(s, jid, metrics={"pairs": 3})
            crud.set_job_status(s, jid, JobStatus.succeeded)
            s.commit()

    def lines(it):
        for line in it:
            if line.startswith("event: progress"):
                reported.release()
            yield line

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    t0 = time.monotonic()
    with api_env.client.stream("GET", f"/jobs/{jid}/events", headers=t.headers) as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        events = _read_events(lines(r.iter_lines()))
    thread.join(5)
    assert time.monotonic() - t0 < 20
    progress = [d for name, d in events if name == "progress"]
    assert progress[0]["status"] == "queued" and progress[0]["progress"] == 0
    seen = [(d["progress"], d["stage"]) for d in progress if d["status"] == "running"]
    assert seen == steps  # every change, in order, once
    assert progress[-1]["status"] == "succeeded" and progress[-1]["progress_percent"] == 100.0
    assert progress[-1]["metrics"] == {"pairs": 3}
    assert events[-1] == ("end", {"id": jid, "status": "succeeded", "outcome": None})

    # a finished job: its state, then the end, at once
    with api_env.client.stream("GET", f"/jobs/{jid}/events", headers=t.headers) as r:
        events = _read_events(r.iter_lines())
    assert [name for name, _ in events] == ["progress", "end"]


def test_event_streams_share_one_poll_of_the_database(api_env, make_jpeg) -> None:
    """200 streams of 4 jobs (api.events.JobWatch): one query per poll for all of them, not one per
    stream, and a change reaches every stream of its job within a poll."""
    import asyncio

    from api.events import JobWatch

    t = api_env.tenant()
    jobs = [_job(api_env, t, make_jpeg)[1] for _ in range(4)]
    watch = JobWatch(api_env.app.state.sessionmaker, poll_s=0.05)

    async def follower(job_id: str, seen: list) -> None:
        async for snap in watch.follow(job_id, 1.0):
            seen.append(snap["status"])
            if snap["status"] == "running":
                return

    async def burst() -> tuple[list[list[str]], int, float]:
        seens: list[list[str]] = [[] for _ in range(200)]
        tasks = [asyncio.create_task(follower(jobs[i % 4], seens[i])) for i in range(200)]
        await asyncio.sleep(0.5)
        polls_before = watch.polls
        with api_env.session() as s:
            for job_id in jobs:
                crud.set_job_status(s, job_id, JobStatus.running)
            s.commit()
        t0 = time.monotonic()
        await asyncio.wait_for(asyncio.gather(*tasks), 10)
        return seens, polls_before, time.monotonic() - t0

    seens, polls, took = asyncio.run(burst())
    assert all(seen[0] == "queued" and seen[-1] == "running" for seen in seens)
    assert polls <= 0.5 / 0.05 + 2  # one query per poll for the 200 streams (their first reads aside)
    assert took < 2.0, took


def test_results_as_named_bundles(api_env, make_jpeg) -> None:
    """GET /jobs/{id}/bundles/gis.zip and colmap.zip: the combined model's GIS layers, or its COLMAP
    model and georeference, each with the report, in one zip streamed from the storage; 404 for an
    unknown bundle, a job with nothing for it yet, and another tenant's job."""
    import io
    import zipfile

    c, t = api_env.client, api_env.tenant()
    pid, jid = _job(api_env, t, make_jpeg)
    assert c.get(f"/jobs/{jid}/bundles/gis.zip", headers=t.headers).status_code == 404  # nothing yet
    files = {
        "combined/gis/cameras.gpkg": os.urandom(3_000_000),  # larger than a chunk: streamed in parts
        "combined/gis/points.las": b"LASF" + os.urandom(1000),
        "combined/sparse/cameras.bin": os.urandom(200),
        "combined/sparse/images.bin": os.urandom(300),
        "combined/georef.json": b'{"crs": "EPSG:32633"}',
        "combined/report.json": b'{"NRI": {}}',
        "matches/v1.h5": os.urandom(100),
        "views/ortho/orthophoto.tif": b"II*\x00" + os.urandom(500),
    }
    with api_env.session() as s:
        for name, data in files.items():
            stage, rel = (
                ("combined_sfm", name.split("/", 1)[1])
                if name.startswith("combined/")
                else ("render_views", name)
                if name.startswith("views/")
                else ("match_views", name)
            )
            key = job_key(t.id, pid, jid, stage, rel)
            api_env.storage.put_bytes(key, data)
            crud.record_artifact(s, jid, "x", name, key, len(data), hashlib.sha256(data).hexdigest(), None)
        s.commit()
    for bundle, names in (
        ("gis", {"combined/gis/cameras.gpkg", "combined/gis/points.las", "views/ortho/orthophoto.tif",
                 "combined/report.json"}),
        ("colmap", {"combined/sparse/cameras.bin", "combined/sparse/images.bin", "combined/georef.json",
                    "combined/report.json"}),
    ):  # fmt: skip
        r = c.get(f"/jobs/{jid}/bundles/{bundle}.zip", headers=t.headers)
        assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
        assert f"midview-{jid[:8]}-{bundle}.zip" in r.headers["content-disposition"]
        with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
            assert zf.testzip() is None and set(zf.namelist()) == names
            assert all(zf.read(n) == files[n] for n in names)
    r = c.get(f"/jobs/{jid}/bundles/everything.zip", headers=t.headers)
    assert r.status_code == 404 and "bundles are gis, colmap" in r.text
    assert c.get(f"/jobs/{jid}/bundles/gis.zip", headers=api_env.tenant().headers).status_code == 404


def test_artifact_listing_and_downloads(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid, jid = _job(api_env, t, make_jpeg)
    data = json.dumps({"ncm": 123}).encode()
    key = job_key(t.id, pid, jid, "reduce", "report.json")
    api_env.storage.put_bytes(key, data, content_type="application/json")
    with api_env.session() as s:
        crud.record_artifact(
            s,
            jid,
            "report",
            "reduce/report.json",
            key,
            len(data),
            hashlib.sha256(data).hexdigest(),
            "application/json",
        )
        crud.record_artifact(s, jid, "model", "missing.ply", job_key(t.id, pid, jid, "x", "missing.ply"))
        s.commit()
    arts = {a["name"]: a for a in c.get(f"/jobs/{jid}/artifacts", headers=t.headers).json()}
    assert set(arts) == {"reduce/report.json", "missing.ply"}
    art = arts["reduce/report.json"]
    assert art["size_bytes"] == len(data) and art["kind"] == "report" and art["job_id"] == jid
    if api_env.s3:  # a presigned URL: no API key needed
        assert art["download_url"].startswith(api_env.settings.s3_endpoint_url)
        assert httpx.get(art["download_url"], timeout=10).content == data
    else:  # the API's own download route
        assert art["download_url"] == f"http://testserver/artifacts/{art['id']}/download"
        assert c.get(art["download_url"]).status_code == 401
        assert c.get(art["download_url"], headers=t.headers).content == data
    r = c.get(f"/artifacts/{art['id']}/download", headers=t.headers)
    assert r.status_code == 200 and r.content == data
    assert r.headers["content-type"] == "application/json"
    assert 'filename="report.json"' in r.headers["content-disposition"]
    assert c.get(f"/artifacts/{art['id']}", headers=t.headers).json()["sha256"] == art["sha256"]
    r = c.get(f"/artifacts/{arts['missing.ply']['id']}/download", headers=t.headers)
    assert r.status_code == 404 and "missing" in r.json()["detail"]
    assert c.get(f"/artifacts/{uuid.uuid4()}", headers=t.headers).status_code == 404


def _match_file(path: Path, n_ag: int = 5) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    kps = {
        n: rng.uniform(0, 60, (12, 2)).astype(np.float32)
        for n in ("aerial/A1.jpg", "aerial/A2.jpg", "ground/G1.jpg", "ground/G2.jpg")
    }
    with MatchFile(path, "w", method="midview") as mf:
        for name, kp in kps.items():
            mf.add_keypoints(name, kp, (64, 48) if name.startswith("aerial") else (32, 24))
        m = np.stack([np.arange(n_ag), np.arange(n_ag)[::-1] + 2], axis=1)
        inliers = np.arange(n_ag) % 2 == 0
        mf.add_pair(PairMatches("aerial/A1.jpg", "ground/G1.jpg", m, np.linspace(1, 0, n_ag), inliers))
        views = np.array([mf.view_index("v0"), mf.view_index("v1"), mf.view_index("v0")])
        gm = np.array([[0, 3], [1, 4], [2, 5]])  # stored ground first: (G2 index, A1 index)
        mf.add_pair(PairMatches("ground/G2.jpg", "aerial/A1.jpg", gm, np.ones(3), None, views))
        mf.add_pair(PairMatches("aerial/A1.jpg", "aerial/A2.jpg", np.array([[0, 0]]), np.ones(1)))
    return kps


def _record(env, tenant, pid: str, jid: str, path: Path, name: str = "matches.h5") -> None:
    key = job_key(tenant.id, pid, jid, "reduce", name)
    env.storage.put_file(key, path)
    with env.session() as s:
        crud.record_artifact(s, jid, "matches", name, key, path.stat().st_size)
        s.commit()


def test_pairs_of_a_match_file(api_env, make_jpeg, tmp_path: Path) -> None:
    c, t = api_env.client, api_env.tenant()
    pid, jid = _job(api_env, t, make_jpeg)
    r = c.get(f"/jobs/{jid}/pairs", headers=t.headers)
    assert r.status_code == 404 and "no match file" in r.json()["detail"]
    kps = _match_file(tmp_path / "m.h5")
    _record(api_env, t, pid, jid, tmp_path / "m.h5")

    r = c.get(f"/jobs/{jid}/pairs", headers=t.headers)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["artifact"] == "matches.h5" and body["method"] == "midview" and body["total"] == 2
    assert body["pairs"] == [  # aerial first, aerial-aerial pairs left out
        {"aerial": "aerial/A1.jpg", "ground": "ground/G1.jpg", "num_matches": 5, "num_inliers": 3},
        {"aerial": "aerial/A1.jpg", "ground": "ground/G2.jpg", "num_matches": 3, "num_inliers": None},
    ]
    assert c.get(f"/jobs/{jid}/pairs", params={"offset": 1, "limit": 1}, headers=t.headers).json()[
        "pairs"
    ] == [body["pairs"][1]]

    one = c.get(f"/jobs/{jid}/pairs/aerial/A1.jpg/ground/G2.jpg", headers=t.headers).json()
    assert one["num_matches"] == 3 and one["aerial_size"] == [64, 48] and one["ground_size"] == [32, 24]
    np.testing.assert_allclose(one["aerial_xy"], kps["aerial/A1.jpg"][[3, 4, 5]], rtol=1e-6)
    np.testing.assert_allclose(one["ground_xy"], kps["ground/G2.jpg"][[0, 1, 2]], rtol=1e-6)
    assert one["views"] == ["v0", "v1", "v0"] and one["inliers"] is None

    r = c.get(
        f"/jobs/{jid}/pairs/aerial/A1.jpg/ground/G1.jpg", params={"inliers_only": True}, headers=t.headers
    )
    g1 = r.json()
    assert g1["num_matches"] == 5 and g1["num_inliers"] == 3 and g1["inliers"] == [True] * 3
    np.testing.assert_allclose(g1["aerial_xy"], kps["aerial/A1.jpg"][[0, 2, 4]], rtol=1e-6)
    np.testing.assert_allclose(g1["ground_xy"], kps["ground/G1.jpg"][[6, 4, 2]], rtol=1e-6)
    assert g1["scores"] == [1.0, 0.5, 0.0]

    assert c.get(f"/jobs/{jid}/pairs/aerial/A2.jpg/ground/G1.jpg", headers=t.headers).status_code == 404
    assert c.get(f"/jobs/{jid}/pairs/aerial/NOPE.jpg/ground/G1.jpg", headers=t.headers).status_code == 404
    r = c.get(f"/jobs/{jid}/pairs", params={"artifact": "other.h5"}, headers=t.headers)
    assert r.status_code == 404

    # a replaced match file is read again, not served from the cache
    _match_file(tmp_path / "m2.h5", n_ag=7)
    _record(api_env, t, pid, jid, tmp_path / "m2.h5")
    assert c.get(f"/jobs/{jid}/pairs", headers=t.headers).json()["pairs"][0]["num_matches"] == 7
    # not a match file
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    _record(api_env, t, pid, jid, tmp_path / "bad.h5", name="bad.h5")
    r = c.get(f"/jobs/{jid}/pairs", params={"artifact": "bad.h5"}, headers=t.headers)
    assert r.status_code == 422


def test_deleting_an_image_while_a_job_is_created_never_removes_a_frozen_input(
    api_env, make_jpeg, monkeypatch
) -> None:
    """DELETE of an image and POST of a job at once, 100 rounds: either the delete wins (the job's frozen
    inputs lack the image) or the job does (the delete answers 409); never a 204 for an image the new
    job froze. The project's row serialises the two (crud.lock_project)."""
    from concurrent.futures import ThreadPoolExecutor

    from conftest import jobbable_project

    from api.ratelimit import MemoryRateLimiter
    from shared.db.models import Job

    # 500 requests in a few seconds from one key: past its burst, which is not what this test is about
    monkeypatch.setattr(api_env.app.state, "rate_limiter", MemoryRateLimiter(10**6, 10**6))
    c, t = api_env.client, api_env.tenant()
    pid = jobbable_project(c, t.headers, make_jpeg, aerial=4)
    url = f"/projects/{pid}/images/aerial/A4.jpg"
    outcomes = {"delete won": 0, "job won": 0}
    with ThreadPoolExecutor(2) as pool:
        for k in range(100):
            if c.get(url, headers=t.headers).status_code == 404:
                files = {"f": ("A4.jpg", make_jpeg(seed=3))}
                r = c.post(
                    f"/projects/{pid}/images", params={"set": "aerial"}, files=files, headers=t.headers
                )
                assert r.status_code in (200, 201), r.text
            deleting = pool.submit(c.delete, url, headers=t.headers)
            creating = pool.submit(c.post, f"/projects/{pid}/jobs", json={}, headers=t.headers)
            deleted, created = deleting.result(), creating.result()
            assert deleted.status_code in (204, 409), deleted.text
            if created.status_code != 201:  # the POS names an image the delete removed: 4xx, nothing made
                assert 400 <= created.status_code < 500, created.text
                continue
            job_id = created.json()["id"]
            with api_env.session() as s:
                frozen = "aerial/A4.jpg" in (s.get(Job, job_id).inputs or {}).get("images", {})
            assert not (deleted.status_code == 204 and frozen), f"round {k}: a frozen input was deleted"
            assert deleted.status_code == 204 or frozen, f"round {k}: 409 for an image no job uses"
            outcomes["delete won" if deleted.status_code == 204 else "job won"] += 1
            assert c.post(f"/jobs/{job_id}/cancel", headers=t.headers).status_code == 200
    assert sum(outcomes.values()) >= 50, outcomes
