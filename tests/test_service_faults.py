"""Faults of the distributed service on a timeline: the broker (Redis) crashes and restarts empty while a
stage runs, and a whole worker node (its main process and its pool) is SIGKILLed while a stage runs. In
both the job must be working again within RECOVER_S of the fault, with no one's help but the service's
own reconciler (celery beat in its own process, as in docker-compose.yml), and end with the same results
as a job that met no fault.

The stack is the service's, private to this module: a redis-server this test may crash, a fresh
PostgreSQL database, the session's SeaweedFS bucket, `celery worker` and `celery beat` processes, and the
API in-process (TestClient, Celery dispatcher). The heartbeat settings are shortened (TEST_TIMING) to keep
the suite short; `MIDVIEW_FAULTS_AT_DEFAULTS=1` runs the same test at the service's defaults (heartbeat
every 10 s, stale after 30 s, reconcile every 15 s), which must recover within RECOVER_S as well.
"""

from __future__ import annotations

import os
import signal
import sys
import time
import types
import uuid
from pathlib import Path

import pytest
from conftest import new_tenant, upload_survey, worker_environment
from servers import RedisServer, _spawn, _stop, _tail

pytestmark = pytest.mark.slow

RECOVER_S = 60.0
AT_DEFAULTS = os.environ.get("MIDVIEW_FAULTS_AT_DEFAULTS") == "1"
TEST_TIMING = (
    {} if AT_DEFAULTS else {"heartbeat_every_s": 2.0, "heartbeat_timeout_s": 6.0, "reconcile_every_s": 3.0}
)
OPTIONS = {"stages": ["aerial_sfm"], "sfm_features": "sift", "seed": 0}
SPARSE = ("sfm/sparse/cameras.bin", "sfm/sparse/images.bin", "sfm/sparse/points3D.bin")
ROOT = Path(__file__).resolve().parents[1]


class Node:
    """A `celery worker` (or `celery beat`) subprocess of the private stack."""

    def __init__(self, args: list[str], env: dict[str, str], log: Path, ready: str):
        self.log = log
        self.proc = _spawn(
            [sys.executable, "-m", "celery", "-A", "workers.celery_app", *args], log, ROOT, env
        )
        deadline = time.monotonic() + 90
        while ready not in (log.read_text(errors="replace") if log.exists() else ""):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                _stop(self.proc)
                pytest.fail(f"{args[0]} did not start:\n{_tail(log, 4000)}")
            time.sleep(0.1)

    def kill(self) -> None:
        """SIGKILL the node's whole process group: main process and pool, no shutdown."""
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(5)


@pytest.fixture(scope="module")
def stack(service_settings, tmp_path_factory, request):
    from fastapi.testclient import TestClient

    from api.main import create_app
    from shared.db.session import upgrade_database

    folder = tmp_path_factory.mktemp("faults")
    redis_server = RedisServer(folder)
    redis_server.start()
    url = request.getfixturevalue("postgres_server").create_database()
    upgrade_database(url)
    settings = service_settings.model_copy(
        update={
            "database_url": url,
            "broker_url": redis_server.url,
            "result_backend": redis_server.url,
            "data_dir": folder / "api",
            "work_dir": folder / "work-api",
            **TEST_TIMING,
        }  # fmt: skip
    )
    env = worker_environment(settings, folder / "work")
    env.update({f"MIDVIEW_{k.upper()}": str(v) for k, v in TEST_TIMING.items()})
    nodes: list[Node] = []

    def start_worker(queues: str = "gpu,cpu,reduce,control") -> Node:
        n = len(nodes)
        name = f"fault-{n}-{uuid.uuid4().hex[:4]}@%h"
        args = ["worker", "-Q", queues, "-c", "1", "-P", "prefork", "-l", "INFO", "-n", name,
                "--without-gossip", "--without-mingle", "--without-heartbeat"]  # fmt: skip
        e = {**env, "MIDVIEW_WORK_DIR": str(folder / f"work-{n}")}
        nodes.append(Node(args, e, folder / f"worker-{n}.log", "ready."))
        return nodes[-1]

    beat = Node(
        ["beat", "-l", "INFO", "-s", str(folder / "beat-schedule")],
        env,
        folder / "beat.log",
        "beat: Starting",
    )
    start_worker()
    app = create_app(settings)
    try:
        with TestClient(app) as client:
            tenant = new_tenant(app, "faults")
            yield types.SimpleNamespace(
                client=client, tenant=tenant, redis=redis_server, nodes=nodes, start_worker=start_worker,
                app=app, beat=beat, folder=folder,
            )  # fmt: skip
    finally:
        for node in [*nodes, beat]:
            _stop(node.proc)
        redis_server.stop()


@pytest.fixture(scope="module")
def project(stack, tiny_survey):
    return upload_survey(stack.client, stack.tenant, tiny_survey, None)


def _logs(stack) -> str:
    parts = [f"--- {n.log.name}\n{_tail(n.log, 3000)}" for n in [*stack.nodes, stack.beat]]
    return "\n".join(parts)


def _job(stack, job_id: str) -> dict:
    r = stack.client.get(f"/jobs/{job_id}", headers=stack.tenant.headers)
    assert r.status_code == 200, r.text
    return r.json()


def _start_job(stack, project: str) -> str:
    r = stack.client.post(
        f"/projects/{project}/jobs", json={"options": OPTIONS}, headers=stack.tenant.headers
    )
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _wait(stack, job_id: str, what: str, until, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        job = _job(stack, job_id)
        if until(job):
            return job
        if job["status"] in ("failed", "cancelled") or time.monotonic() > deadline:
            pytest.fail(f"job {job_id}: {what} not seen ({job['status']}): {job}\n{_logs(stack)}")
        time.sleep(0.1)


def _running(job: dict) -> bool:
    return any(st["status"] == "running" for st in job["stages"])


def _sparse_digests(stack, job_id: str) -> dict[str, str]:
    r = stack.client.get(f"/jobs/{job_id}/artifacts", headers=stack.tenant.headers)
    assert r.status_code == 200, r.text
    return {a["name"]: a["sha256"] for a in r.json() if a["name"] in SPARSE}


@pytest.fixture(scope="module")
def reference(stack, project) -> dict[str, str]:
    """The sparse model of a job that met no fault."""
    job_id = _start_job(stack, project)
    job = _wait(stack, job_id, "success", lambda j: j["status"] == "succeeded", 180)
    assert [(st["stage"], st["status"]) for st in job["stages"]] == [("aerial_sfm", "succeeded")]
    digests = _sparse_digests(stack, job_id)
    assert set(digests) == set(SPARSE), digests
    return digests


def _recovered(stack, job_id: str, t_fault: float) -> tuple[dict, float]:
    """Wait for the stage to run again (a second stage run) or the job to finish; (job, seconds from the
    fault to that)."""
    job = _wait(
        stack, job_id, "the stage running again",
        lambda j: len(j["stages"]) > 1 or j["status"] == "succeeded", RECOVER_S + 60,
    )  # fmt: skip
    return job, time.monotonic() - t_fault


def test_redis_crash_and_restart_while_a_stage_runs(stack, project, reference):
    """Redis is SIGKILLed while aerial_sfm runs and started again empty: the queued messages, the task's
    heartbeat key and the running task (cancelled by the worker on the connection loss) are gone; the
    reconciler sees a stale heartbeat and nothing of the job in the broker, and dispatches it again."""
    job_id = _start_job(stack, project)
    _wait(stack, job_id, "aerial_sfm running", _running, 120)
    t_fault = time.monotonic()
    stack.redis.crash()
    stack.redis.start()
    job, recovered_s = _recovered(stack, job_id, t_fault)
    job = _wait(stack, job_id, "success", lambda j: j["status"] == "succeeded", 240)
    print(
        f"\nRedis restart: the job worked again {recovered_s:.1f} s after the crash; stages {job['stages']}"
    )
    assert recovered_s < RECOVER_S, (recovered_s, job)
    assert _sparse_digests(stack, job_id) == reference
    if len(job["stages"]) > 1:  # the task was lost with the broker: given up and dispatched again
        first = job["stages"][0]
        assert first["status"] == "failed" and "no task or message of it in the broker" in first["error"], (
            first
        )
        assert job["stages"][-1]["status"] == "succeeded"


def test_worker_node_sigkilled_while_a_stage_runs(stack, project, reference):
    """The node running aerial_sfm is SIGKILLed (main process and pool, its message left in `unacked`)
    and a new node starts, as an orchestrator would start one: the reconciler finds the stale heartbeat
    and the dead node silent to a ping, gives the stage up and dispatches it again; the new node runs it."""
    job_id = _start_job(stack, project)
    job = _wait(stack, job_id, "aerial_sfm running", _running, 120)
    dead = stack.nodes[-1]
    t_fault = time.monotonic()
    dead.kill()
    stack.start_worker()
    job, recovered_s = _recovered(stack, job_id, t_fault)
    job = _wait(stack, job_id, "success", lambda j: j["status"] == "succeeded", 240)
    print(
        f"\nworker SIGKILL: the job worked again {recovered_s:.1f} s after the kill; stages {job['stages']}"
    )
    assert recovered_s < RECOVER_S, (recovered_s, job)
    first, last = job["stages"][0], job["stages"][-1]
    assert (
        first["status"] == "failed" and "abandoned" in first["error"] and "does not answer" in first["error"]
    )
    assert last["status"] == "succeeded" and last["node"] != first["node"], job["stages"]
    assert _sparse_digests(stack, job_id) == reference


def test_a_message_lost_between_stages(stack, project, reference):
    """The broker loses the message of a job's next task while it waits in a queue between two stages
    (aerial_sfm succeeded, `finalize` waits on the reduce queue, which no worker serves yet; Redis
    crashes and restarts empty). The reconciler finds the job with no stage running and nothing of it
    in the broker and dispatches it again within RECOVER_S; the stage that succeeded is not run again."""
    for node in stack.nodes:
        _stop(node.proc)
    stack.start_worker("gpu,cpu,control")
    job_id = _start_job(stack, project)
    between = _wait(
        stack, job_id, "aerial_sfm succeeded, finalize waiting",
        lambda j: [st["status"] for st in j["stages"]] == ["succeeded"], 180,
    )  # fmt: skip
    assert between["status"] == "running", between
    time.sleep(1.0)  # the message is in the reduce queue, no worker takes it
    t_fault = time.monotonic()
    stack.redis.crash()
    stack.redis.start()
    stack.start_worker("reduce")
    job = _wait(stack, job_id, "success", lambda j: j["status"] == "succeeded", RECOVER_S + 60)
    recovered_s = time.monotonic() - t_fault
    print(f"\nlost message between stages: the job succeeded {recovered_s:.1f} s after the crash")
    assert recovered_s < RECOVER_S, (recovered_s, job)
    assert [st["status"] for st in job["stages"]][0] == "succeeded"
    assert _sparse_digests(stack, job_id) == reference
