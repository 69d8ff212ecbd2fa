"""Idempotent job creation (client keys) and campaigns through the API, on both backends. A test plays
the worker by moving job rows through shared.db.crud; the dispatcher records what it was asked."""

from __future__ import annotations

import uuid

from conftest import jobbable_project

from shared.db import crud
from shared.db.models import JobStatus, StageStatus


def _key() -> str:
    return f"k-{uuid.uuid4().hex[:12]}"


def test_a_repeated_creation_with_a_key_returns_the_first_job(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    pid = jobbable_project(c, t.headers, make_jpeg)
    key = _key()
    body = {"key": key, "options": {"splat_steps": 500}}
    first = c.post(f"/projects/{pid}/jobs", json=body, headers=t.headers)
    assert first.status_code == 201 and first.json()["key"] == key
    submits = [x for x in api_env.dispatcher.calls if x[:2] == ("submit", first.json()["id"])]
    again = c.post(f"/projects/{pid}/jobs", json=body, headers=t.headers)
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
    # queued once: the repeat dispatched nothing
    assert [x for x in api_env.dispatcher.calls if x[:2] == ("submit", first.json()["id"])] == submits
    other = c.post(
        f"/projects/{pid}/jobs", json={"key": key, "options": {"splat_steps": 600}}, headers=t.headers
    )
    assert other.status_code == 409 and first.json()["id"] in other.json()["detail"]
    listed = c.get(f"/projects/{pid}/jobs", params={"key": key}, headers=t.headers).json()
    assert [j["id"] for j in listed] == [first.json()["id"]]
    assert c.get(f"/projects/{pid}/jobs", params={"key": "nope"}, headers=t.headers).json() == []
    assert len(c.get(f"/projects/{pid}/jobs", headers=t.headers).json()) == 1
    bad = c.post(f"/projects/{pid}/jobs", json={"key": "../x"}, headers=t.headers)
    assert bad.status_code == 422


def test_projects_filter_by_name(api_env) -> None:
    c, t = api_env.client, api_env.tenant()
    name = f"survey-{uuid.uuid4().hex[:6]}"
    pid = c.post("/projects", json={"name": name}, headers=t.headers).json()["id"]
    c.post("/projects", json={"name": name + "-b"}, headers=t.headers)
    assert [p["id"] for p in c.get("/projects", params={"name": name}, headers=t.headers).json()] == [pid]


def _play_stage(api_env, job_id: str, stage: str, status: StageStatus, metrics: dict | None = None) -> None:
    """As a worker would: run `stage` to `status`, and the job to succeeded or failed with it."""
    with api_env.session() as s:
        crud.set_job_status(s, job_id, JobStatus.running)
        run = crud.start_stage(s, job_id, stage)
        crud.finish_stage(s, run, status, error="disk full" if status == StageStatus.failed else None)
        if metrics:
            crud.update_job_results(s, job_id, metrics=metrics)
        final = JobStatus.succeeded if status == StageStatus.succeeded else JobStatus.failed
        crud.set_job_status(s, job_id, final, error="combined_sfm: disk full" if final == "failed" else None)
        s.commit()


def test_campaign_status_and_retry_from_the_failed_stage(api_env, make_jpeg) -> None:
    c, t = api_env.client, api_env.tenant()
    name = f"campaign-{uuid.uuid4().hex[:6]}"
    r = c.post("/campaigns", json={"name": name, "max_concurrent": 2}, headers=t.headers)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    again = c.post("/campaigns", json={"name": name, "max_concurrent": 2}, headers=t.headers)
    assert again.status_code == 200 and again.json()["id"] == cid  # idempotent by name
    assert (
        c.post("/campaigns", json={"name": name, "max_concurrent": 3}, headers=t.headers).status_code == 409
    )

    jobs = []
    for i in range(3):
        pid = jobbable_project(c, t.headers, make_jpeg, name=f"{name}-{i}")
        r = c.post(f"/projects/{pid}/jobs", json={"key": f"s{i}", "campaign_id": cid}, headers=t.headers)
        assert r.status_code == 201 and r.json()["campaign_id"] == cid
        jobs.append(r.json()["id"])
    outcome = {"outcome": {"registered": {"aerial": 3, "ground": 1}, "images": {"aerial": 3, "ground": 1},
                           "result": "ok"}}  # fmt: skip
    _play_stage(api_env, jobs[0], "combined_sfm", StageStatus.succeeded, outcome)
    _play_stage(api_env, jobs[1], "combined_sfm", StageStatus.failed)

    st = c.get(f"/campaigns/{cid}", headers=t.headers).json()
    assert st["jobs_by_status"] == {"succeeded": 1, "failed": 1, "queued": 1}
    assert st["active"] == 1 and not st["done"]
    assert (st["ground_registered"], st["ground_images"]) == (1, 1)
    by_id = {j["id"]: j for j in st["jobs"]}
    assert by_id[jobs[1]]["failed_stage"] == "combined_sfm" and by_id[jobs[0]]["registered"]["ground"] == 1
    assert by_id[jobs[2]]["project_name"] == f"{name}-2" and by_id[jobs[2]]["key"] == "s2"
    listed = {x["id"]: x for x in c.get("/campaigns", headers=t.headers).json()}
    assert listed[cid]["jobs_by_status"] == st["jobs_by_status"]

    # one slot free (one job is queued): the failed job reruns from the stage that failed
    r = c.post(f"/campaigns/{cid}/retry", json={}, headers=t.headers)
    assert r.status_code == 200, r.text
    assert [j["id"] for j in r.json()["rerun"]] == [jobs[1]] and r.json()["waiting"] == []
    assert api_env.dispatcher.calls[-1] == ("submit", jobs[1], "combined_sfm")
    rerun = c.get(f"/jobs/{jobs[1]}", headers=t.headers).json()
    assert rerun["status"] == "queued" and rerun["attempt"] == 2

    # no free slot: a failed job waits
    _play_stage(api_env, jobs[1], "combined_sfm", StageStatus.failed)
    pid = jobbable_project(c, t.headers, make_jpeg, name=f"{name}-3")
    extra = c.post(f"/projects/{pid}/jobs", json={"campaign_id": cid}, headers=t.headers).json()["id"]
    assert extra
    r = c.post(f"/campaigns/{cid}/retry", json={}, headers=t.headers).json()
    assert r["rerun"] == [] and r["waiting"] == [jobs[1]]
    r = c.post(f"/campaigns/{cid}/retry", json={"limit": 1, "from_failed_stage": False}, headers=t.headers)
    assert r.json()["rerun"][0]["id"] == jobs[1]  # an explicit limit overrides the slots
    assert api_env.dispatcher.calls[-1] == ("submit", jobs[1], None)


def test_campaigns_are_the_tenants_own(api_env, make_jpeg) -> None:
    c, a, b = api_env.client, api_env.tenant(), api_env.tenant()
    cid = c.post("/campaigns", json={"name": "mine"}, headers=a.headers).json()["id"]
    assert c.get(f"/campaigns/{cid}", headers=b.headers).status_code == 404
    assert c.post(f"/campaigns/{cid}/retry", headers=b.headers).status_code == 404
    assert cid not in {x["id"] for x in c.get("/campaigns", headers=b.headers).json()}
    pid = jobbable_project(c, b.headers, make_jpeg)
    r = c.post(f"/projects/{pid}/jobs", json={"campaign_id": cid}, headers=b.headers)
    assert r.status_code == 404 and "campaign" in r.json()["detail"]
    assert c.get(f"/projects/{pid}/jobs", headers=b.headers).json() == []  # nothing was made
