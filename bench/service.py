"""Service benchmark: API latency (GET /jobs/{id} vs GET /healthz), upload throughput through the API vs
direct S3, and the match_views stage time with 1 and 2 Celery worker processes.

Starts its own throwaway PostgreSQL database, SeaweedFS (`weed mini`), Redis db, uvicorn and Celery
workers (helpers of tests/servers.py); everything is stopped and removed at the end.

    python bench/service.py [--clients 50] [--requests 2000] [--upload-mb 64] [--skip-workers] [--json F]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import servers  # noqa: E402  (tests/servers.py: PostgreSQL, SeaweedFS, uvicorn helpers)

WORKER_OPTIONS = {  # as tests/test_service_e2e.py: small enough for `tiny` on 2 cores
    "view_planner": "ground-aware",
    "views_per_ground_image": 1,
    "splat_steps": 1000,
    "splat_max_width": 240,
    "block_steps": 300,
    "block_px": 120,  # several blocks on `tiny` (one at the default 640 px): a fan-out to measure
    "max_keypoints": 1024,
    "seed": 0,
}
JOB_TIMEOUT_S = 600


def wait_until(check: Any, timeout: float, what: str, proc: Any = None, log: Path | None = None) -> None:
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(
                f"{what}: process exited {proc.returncode}\n{servers._tail(log) if log else ''}"
            )
        try:
            if check():
                return
        except Exception as e:  # noqa: BLE001 - retried until the deadline
            last = e
        time.sleep(0.2)
    raise RuntimeError(f"{what} not ready after {timeout} s ({last})\n{servers._tail(log) if log else ''}")


class Stack:
    """The servers of one benchmark run; stop() cleans up whatever was started."""

    def __init__(self) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="mvbench-"))
        self.procs: list[Any] = []
        self.pg: servers.PostgresServer | None = None
        self.redis_db: tuple[str, int] | None = None
        self.weed_ports: list[int] = []
        self.s3: dict[str, str] | None = None
        self.env: dict[str, str] = {}
        self.notes: list[str] = []

    # PostgreSQL
    def start_postgres(self) -> str:
        from shared.db.session import upgrade_database

        user = servers._pg_user()
        if user is None:
            servers._start_local_postgres()
            wait_until(lambda: servers._pg_user() is not None, 15, "PostgreSQL")
            user = servers._pg_user()
        self.pg = servers.PostgresServer(user=user)
        url = self.pg.create_database()
        upgrade_database(url)
        return url

    # Redis: an empty db of the local server, else a private redis-server
    def start_redis(self) -> str:
        import redis

        try:
            redis.Redis(host="127.0.0.1", port=6379, socket_connect_timeout=1).ping()
            for db in range(15, 0, -1):
                r = redis.Redis(host="127.0.0.1", port=6379, db=db)
                if r.dbsize() == 0:
                    self.redis_db = ("127.0.0.1:6379", db)
                    return f"redis://127.0.0.1:6379/{db}"
        except redis.RedisError:
            pass
        (port,) = servers.free_ports(1)
        folder = self.tmp / "redis"
        folder.mkdir()
        args = [
            "redis-server",
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "no",
        ]
        proc = servers._spawn([*args, "--dir", str(folder)], folder / "redis.log")
        self.procs.append(proc)
        wait_until(lambda: redis.Redis(port=port).ping(), 10, "redis-server", proc, folder / "redis.log")
        return f"redis://127.0.0.1:{port}/0"

    # SeaweedFS S3
    def start_s3(self) -> dict[str, str] | None:
        import boto3
        from botocore.config import Config

        weed = servers.weed_binary()
        if weed is None:
            self.notes.append("no `weed` binary: local storage")
            return None
        folder = Path(tempfile.mkdtemp(prefix="w", dir="/tmp"))  # short path for its unix sockets
        self.weed_folder = folder
        access, secret = "midview-bench", uuid.uuid4().hex
        identity = {
            "name": "midview-bench",
            "credentials": [{"accessKey": access, "secretKey": secret}],
            "actions": ["Admin", "Read", "Write", "List", "Tagging"],
        }
        (folder / "s3.json").write_text(json.dumps({"identities": [identity]}))
        self.weed_ports = [*servers.free_ports(8), *servers.free_port_pair()]
        log = folder / "weed.log"
        env = {**os.environ, "TMPDIR": str(folder)}
        cmd = servers.weed_mini_command(weed, folder, self.weed_ports, folder / "s3.json")
        proc = servers._spawn(cmd, log, cwd=folder, env=env)
        self.procs.append(proc)
        s3 = {
            "endpoint": f"http://127.0.0.1:{self.weed_ports[6]}",
            "access": access,
            "secret": secret,
            "bucket": f"midview-bench-{uuid.uuid4().hex[:8]}",
        }
        client = boto3.client(
            "s3",
            endpoint_url=s3["endpoint"],
            aws_access_key_id=access,
            aws_secret_access_key=secret,
            region_name="us-east-1",
            config=Config(connect_timeout=1, read_timeout=10, retries={"max_attempts": 1}),
        )
        try:
            wait_until(
                lambda: servers._s3_round_trip(client, s3["bucket"]) or True, 40, "SeaweedFS", proc, log
            )
        except RuntimeError as e:
            self.notes.append(f"SeaweedFS did not start ({str(e).splitlines()[0]}): local storage")
            return None
        self.s3 = s3
        return s3

    def s3_client(self) -> Any:
        import boto3

        assert self.s3 is not None
        return boto3.client(
            "s3",
            endpoint_url=self.s3["endpoint"],
            aws_access_key_id=self.s3["access"],
            aws_secret_access_key=self.s3["secret"],
            region_name="us-east-1",
        )

    def start(self) -> None:
        db_url = self.start_postgres()
        broker = self.start_redis()
        s3 = self.start_s3()
        env = {k: v for k, v in os.environ.items() if not k.startswith("MIDVIEW_")}
        values = {
            "DATA_DIR": self.tmp / "api",
            "WORK_DIR": self.tmp / "work-api",
            "UPLOAD_TMP_DIR": self.tmp,
            "DATABASE_URL": db_url,
            "BROKER_URL": broker,
            "RESULT_BACKEND": broker,
            "DISPATCHER": "celery",
            "NUM_THREADS": 1,
            "LOG_LEVEL": "WARNING",
            "RATE_LIMIT_PER_MINUTE": int(
                os.environ.get("BENCH_RATE", 10**9)
            ),  # one key floods: the limiter counts (in Redis) but never says 429
        }
        if s3 is not None:
            values.update(
                STORAGE="s3",
                S3_ENDPOINT_URL=s3["endpoint"],
                S3_BUCKET=s3["bucket"],
                S3_REGION="us-east-1",
                S3_ACCESS_KEY=s3["access"],
                S3_SECRET_KEY=s3["secret"],
            )
        else:
            values.update(STORAGE="local", STORAGE_ROOT=self.tmp / "storage")
        env.update({f"MIDVIEW_{k}": str(v) for k, v in values.items()})
        env["PYTHONUNBUFFERED"] = "1"
        env["OMP_NUM_THREADS"] = "1"
        self.env = env

    def start_api(self, workers: int = 1) -> str:
        server = servers.start_uvicorn(self.env, self.tmp / "uvicorn.log", cwd=ROOT, workers=workers)
        self.procs.append(server.proc)
        return server.base_url

    def start_worker(self, i: int) -> Any:
        folder = self.tmp / f"worker{i}"
        folder.mkdir()
        log = folder / "worker.log"
        # one worker process per core, as a deployment sizes its cpu workers: the numba rasterizer of a
        # block single-threaded (by default it takes every core, and two workers would share them)
        env = {
            **self.env,
            "MIDVIEW_WORK_DIR": str(folder / "work"),
            "MIDVIEW_LOG_LEVEL": "INFO",
            "NUMBA_NUM_THREADS": "1",
        }
        from workers.celery_app import QUEUES

        args = [sys.executable, "-m", "celery", "-A", "workers.celery_app", "worker", "-Q", ",".join(QUEUES),
                "-c", "1", "-P", "prefork", "-l", "INFO", "-n", f"mvbench{i}-{uuid.uuid4().hex[:6]}@%h",
                "--without-gossip", "--without-mingle", "--without-heartbeat"]  # fmt: skip
        proc = servers._spawn(args, log, cwd=ROOT, env=env)
        self.procs.append(proc)
        wait_until(lambda: "ready." in log.read_text(errors="replace"), 90, f"worker {i}", proc, log)
        return proc

    def stop(self) -> None:
        for proc in reversed(self.procs):
            with contextlib.suppress(Exception):
                servers._stop(proc, timeout=10)
        if self.pg is not None:
            with contextlib.suppress(Exception):
                self.pg.drop_all()
        if self.redis_db is not None:
            import redis

            with contextlib.suppress(Exception):
                redis.Redis(host="127.0.0.1", port=6379, db=self.redis_db[1]).flushdb()
        for port in self.weed_ports:
            for sock in Path("/tmp").glob(f"seaweedfs-*-{port}.sock"):
                sock.unlink(missing_ok=True)
        if getattr(self, "weed_folder", None) is not None:
            shutil.rmtree(self.weed_folder, ignore_errors=True)
        shutil.rmtree(self.tmp, ignore_errors=True)


# 1. latency
async def hammer(base: str, path: str, headers: dict[str, str], clients: int, n: int) -> dict[str, float]:
    import httpx

    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    latencies: list[float] = []
    errors = 0
    remaining = n

    async with httpx.AsyncClient(base_url=base, headers=headers, limits=limits, timeout=60) as client:
        for _ in range(min(clients, 50)):  # warm up connections and the app
            await client.get(path)

        async def worker() -> None:
            nonlocal remaining, errors
            while remaining > 0:
                remaining -= 1
                t0 = time.perf_counter()
                r = await client.get(path)
                latencies.append(time.perf_counter() - t0)
                if r.status_code != 200:
                    errors += 1

        t0 = time.perf_counter()
        await asyncio.gather(*(worker() for _ in range(clients)))
        wall = time.perf_counter() - t0
    latencies.sort()
    q = statistics.quantiles(latencies, n=100, method="inclusive")
    return {"p50": q[49] * 1e3, "p99": q[98] * 1e3, "rps": len(latencies) / wall, "errors": errors}


async def burst(
    base: str, hot: dict[str, str], other: dict[str, str], paths: dict[str, str], n: int, seconds: float
) -> dict[str, Any]:
    """One key's burst of n simultaneous requests, half of them event streams held `seconds`, half
    project reads, while another tenant reads its project and a probe reads /healthz every 50 ms:
    the other tenant's and healthz's p99, and the burst's answers by status (5xx must be none)."""
    import anyio
    import httpx

    codes: dict[int, int] = {}
    seen: dict[str, list[float]] = {"other": [], "healthz": []}
    other_5xx = 0

    async def one(client: httpx.AsyncClient, i: int) -> None:
        try:
            if i % 2:
                async with client.stream("GET", paths["events"], headers=hot) as r:
                    codes[r.status_code] = codes.get(r.status_code, 0) + 1
                    if r.status_code == 200:
                        with anyio.move_on_after(seconds):
                            async for _ in r.aiter_lines():
                                pass
            else:
                r = await client.get(paths["project"], headers=hot)
                codes[r.status_code] = codes.get(r.status_code, 0) + 1
        except httpx.HTTPError:
            codes[-1] = codes.get(-1, 0) + 1

    async def probe(client: httpx.AsyncClient, name: str, path: str, headers: dict[str, str]) -> None:
        nonlocal other_5xx
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t0 = time.perf_counter()
            r = await client.get(path, headers=headers)
            seen[name].append((time.perf_counter() - t0) * 1e3)
            other_5xx += r.status_code >= 500
            await asyncio.sleep(0.05)

    limits = httpx.Limits(max_connections=n + 10, max_keepalive_connections=n + 10)
    async with (
        httpx.AsyncClient(base_url=base, timeout=120, limits=limits) as hot_client,
        httpx.AsyncClient(base_url=base, timeout=120) as probe_client,
    ):
        await probe_client.get("/healthz")
        await asyncio.gather(
            *(one(hot_client, i) for i in range(n)),
            probe(probe_client, "other", paths["other"], other),
            probe(probe_client, "healthz", "/healthz", {}),
        )

    def p99(xs: list[float]) -> float:
        return statistics.quantiles(xs, n=100, method="inclusive")[98] if len(xs) > 1 else float("nan")

    return {
        "burst_other_tenant_p99_ms": round(p99(seen["other"]), 1),
        "burst_healthz_p99_ms": round(p99(seen["healthz"]), 1),
        "burst_5xx": sum(c for s, c in codes.items() if s >= 500) + other_5xx,
        "burst_answers": {str(s): c for s, c in sorted(codes.items())},
        "burst_requests": n,
    }


WRK_REPORT = """
done = function(summary, latency, requests)
  local n = summary.requests
  local errors = summary.errors.status + summary.errors.connect + summary.errors.read
    + summary.errors.write + summary.errors.timeout
  io.write(string.format('WRK {"p50": %f, "p90": %f, "p99": %f, "n": %d, "seconds": %f, "errors": %d}\\n',
    latency:percentile(50) / 1000, latency:percentile(90) / 1000, latency:percentile(99) / 1000,
    n, summary.duration / 1e6, errors))
end
"""


def hammer_wrk(
    base: str,
    path: str,
    headers: dict[str, str],
    clients: int,
    seconds: float,
    suffixes: list[str] | None = None,
) -> dict[str, float]:
    """The same figures as hammer() from wrk (a C load generator: one thread, `clients` connections kept
    alive, each sending its next request when the last one answered), which leaves the API the CPU
    that an asyncio client in Python would take from it on a small machine. With suffixes, request
    path + suffixes[i] in turn (each connection its own, with as many suffixes as clients)."""
    import subprocess

    script = Path(tempfile.mkdtemp()) / "report.lua"
    paths = ""
    if suffixes:
        listed = ", ".join(f'"{path}{x}"' for x in suffixes)
        paths = f"""
local paths = {{{listed}}}
local counter = 0
setup = function(thread) end
init = function(args) end
request = function()
  counter = counter + 1
  return wrk.format(nil, paths[(counter % #paths) + 1])
end
"""
    script.write_text(paths + WRK_REPORT)
    args = ["wrk", "-t", "1", "-c", str(clients), "--timeout", "30s", "-s", str(script)]
    for k, v in headers.items():
        args += ["-H", f"{k}: {v}"]
    subprocess.run([*args, "-d", "2s", base + path], capture_output=True, check=True)  # warm up
    run = subprocess.run(
        [*args, "-d", f"{seconds:.0f}s", base + path], capture_output=True, text=True, check=True
    )
    out = run.stdout
    line = next((ln for ln in out.splitlines() if ln.startswith("WRK ")), None)
    if line is None:
        raise RuntimeError(f"wrk printed no report:\n{out[-2000:]}")
    m = json.loads(line[4:])
    return {
        "p50": m["p50"],
        "p90": m["p90"],
        "p99": m["p99"],
        "rps": m["n"] / m["seconds"],
        "errors": m["errors"],
    }


def gc_pauses(log: Path) -> list[float]:
    """The API's garbage-collector pauses of 20 ms or more (api/gcwatch.py logs them), in ms."""
    text = log.read_text(errors="replace") if log.is_file() else ""
    return [float(m) for m in re.findall(r"gc pause: generation \d+, ([0-9.]+) ms", text)]


# 2. uploads
def make_jpeg(mb: float) -> bytes:
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    sample = rng.integers(0, 256, (256, 256, 3), dtype=np.uint8)
    per_px = len(cv2.imencode(".jpg", sample, [cv2.IMWRITE_JPEG_QUALITY, 95])[1]) / sample.shape[0] ** 2
    side = int((mb * 1024 * 1024 / per_px) ** 0.5)
    img = rng.integers(0, 256, (side, side, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def bench_uploads(stack: Stack, base: str, headers: dict[str, str], project_id: str, mb: float, n: int):
    """(MB, [s per API POST], [s per client upload], s for n client uploads until checked, [s per boto3
    put_object]). The client's uploads and boto3's alternate image by image, so that both meet the same
    machine (a background load moves both)."""
    import httpx

    data = make_jpeg(mb)
    size_mb = len(data) / 1024 / 1024
    api_times = []
    with httpx.Client(base_url=base, headers=headers, timeout=600) as client:
        for i in range(n):
            t0 = time.perf_counter()
            r = client.post(
                f"/projects/{project_id}/images?set=aerial",
                files=[("files", (f"U{i:04d}.jpg", data, "image/jpeg"))],
            )
            api_times.append(time.perf_counter() - t0)
            if r.status_code not in (200, 201):
                raise RuntimeError(f"upload failed {r.status_code}: {r.text[:500]}")
    client_times, direct_times, checked_total = bench_client_uploads(
        stack, base, headers, project_id, data, n
    )
    return size_mb, api_times, client_times, checked_total, direct_times


def bench_client_uploads(
    stack: Stack, base: str, headers: dict[str, str], project_id: str, data: bytes, n: int
) -> tuple[list[float], list[float], float]:
    """Through the client (client/) as `midview submit` uploads: parts in parallel to the presigned S3
    URLs the start gives (or the API with local storage), then completion without waiting (assembly; the
    sha256 and full decode run on the API while the next image travels). Returns ([s per image until
    the service accepted it], [s per boto3 put_object of the same bytes, alternating with them], s for n
    more images one after the other until the service checked the last one)."""
    import tempfile

    from client import MidviewClient, upload_image

    key = headers["Authorization"].split(" ", 1)[1]
    s3 = stack.s3_client() if stack.s3 is not None else None
    times, direct = [], []
    with tempfile.TemporaryDirectory() as tmp, MidviewClient(base, key, timeout=600) as mv:
        path = Path(tmp) / "image.jpg"
        path.write_bytes(data)
        for i in range(n):
            t0 = time.perf_counter()
            upload_image(mv, project_id, f"aerial/C{i:04d}.jpg", path, stored={}, pending={}, wait=False)
            times.append(time.perf_counter() - t0)
            if s3 is not None:
                t0 = time.perf_counter()
                s3.put_object(Bucket=stack.s3["bucket"], Key=f"bench/direct-{i}.jpg", Body=data)
                direct.append(time.perf_counter() - t0)
        mv.wait_uploads_checked(project_id, poll_s=0.02)
        t_all = time.perf_counter()
        for i in range(n):
            upload_image(mv, project_id, f"aerial/K{i:04d}.jpg", path, stored={}, pending={}, wait=False)
        mv.wait_uploads_checked(project_id, poll_s=0.02)
        total = time.perf_counter() - t_all
    return times, direct, total


# 3. workers
def wait_job(client: Any, job_id: str, timeout: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job
        if time.monotonic() > deadline:
            raise RuntimeError(f"job not finished after {timeout} s: {job['status']} {job['current_stage']}")
        time.sleep(0.5)


def bench_workers(stack: Stack, base: str, headers: dict[str, str]) -> dict[str, Any]:
    import json

    import httpx

    from services import synth

    scene = synth.main(synth.confs["tiny"], stack.tmp / "tiny", seed=0)
    out: dict[str, Any] = {}
    with httpx.Client(base_url=base, headers=headers, timeout=600) as c:
        r = c.post("/projects", json={"name": f"tiny-{uuid.uuid4().hex[:6]}"})
        r.raise_for_status()
        pid = r.json()["id"]
        for image_set in ("aerial", "ground"):
            files = [("files", (p.name, p.read_bytes(), "image/jpeg"))
                     for p in sorted((scene / "images" / image_set).iterdir())]  # fmt: skip
            c.post(f"/projects/{pid}/images?set={image_set}", files=files).raise_for_status()
        r = c.post(f"/projects/{pid}/pos", files={"file": ("pos.csv", (scene / "pos.csv").read_bytes())})
        if r.status_code != 200:
            raise RuntimeError(f"POS upload refused ({r.status_code}): {r.text}")
        # the synthetic images carry no EXIF: their intrinsics go through the API
        r = c.put(f"/projects/{pid}/cameras", json=json.loads((scene / "cameras.json").read_text()))
        if r.status_code != 200:
            raise RuntimeError(f"cameras upload refused ({r.status_code}): {r.text}")

        # a fresh job per setting (a rerun is answered from the worker's local cache and matches nothing)
        for workers in (1, 2):
            stack.start_worker(workers)
            t0 = time.monotonic()
            r = c.post(f"/projects/{pid}/jobs", json={"options": WORKER_OPTIONS})
            r.raise_for_status()
            job = wait_job(c, r.json()["id"], JOB_TIMEOUT_S)
            if job["status"] != "succeeded":
                raise RuntimeError(f"job with {workers} workers {job['status']}: {job.get('error')}")
            out[workers] = job["timings"].get("match_views")
            out[f"blocks{workers}"] = job["timings"].get("train_blocks")
            out[f"blocks{workers}_n"] = (job["metrics"].get("train_blocks") or {}).get("blocks")
            out[f"job{workers}_s"] = time.monotonic() - t0
    return out


def upload_section(console, stack, base, headers, project_id, args, rows, figures) -> None:
    """Uploads through the API (one POST; the client's presigned parts) against boto3 put_object."""
    storage = "SeaweedFS S3" if stack.s3 else "local"
    with console.status(f"uploads of {args.upload_mb} MB"):
        size_mb, api_t, client_t, client_total, direct_t = bench_uploads(
            stack, base, headers, project_id, args.upload_mb, args.uploads
        )
    api_mbs = size_mb * len(api_t) / sum(api_t)
    client_mbs = size_mb * len(client_t) / sum(client_t)
    rows.append((
        "upload: one multipart/form-data POST to the API",
        f"{api_mbs:.1f} MB/s",
        f"{len(api_t)} x {size_mb:.1f} MB JPEG, {storage}, median {statistics.median(api_t):.2f} s",
    ))  # fmt: skip
    checked_mbs = size_mb * len(client_t) / client_total
    rows.append((
        "upload: the client (parts in parallel to presigned URLs, then complete, not waiting)",
        f"{client_mbs:.1f} MB/s",
        f"median {statistics.median(client_t):.2f} s an image until the service accepted it",
    ))  # fmt: skip
    rows.append((
        "upload: the client, until the service checked the last image",
        f"{checked_mbs:.1f} MB/s",
        f"{len(client_t)} images in {client_total:.2f} s: sha256 and full decode on the API",
    ))  # fmt: skip
    figures["upload_mb_s_api_post"] = api_mbs
    figures["upload_mb_s_client"] = client_mbs
    figures["upload_mb_s_client_checked"] = checked_mbs
    if direct_t:
        direct_mbs = size_mb * len(direct_t) / sum(direct_t)
        rows.append((
            "boto3 put_object direct", f"{direct_mbs:.1f} MB/s", "same bytes, same S3 server, alternating"
        ))  # fmt: skip
        rows.append(
            ("client / direct", f"x{client_mbs / direct_mbs:.2f}", "what a user of midview submit gets")
        )
        rows.append(("API POST / direct", f"x{api_mbs / direct_mbs:.2f}", ""))
        rows.append(("client until checked / direct", f"x{checked_mbs / direct_mbs:.2f}", ""))
        figures["upload_ratio_vs_boto3"] = client_mbs / direct_mbs
        figures["upload_ratio_vs_boto3_checked"] = checked_mbs / direct_mbs
        figures["upload_ratio_vs_boto3_api_post"] = api_mbs / direct_mbs
    else:
        rows.append(("boto3 put_object direct", "not measured", "no S3 server"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--upload-mb", type=float, default=64)
    ap.add_argument("--uploads", type=int, default=6)
    ap.add_argument("--skip-workers", action="store_true")
    ap.add_argument("--burst", type=int, default=300, help="one key's simultaneous requests (0: none)")
    ap.add_argument("--skip-uploads", action="store_true")
    ap.add_argument("--load", choices=["wrk", "httpx"], help="load generator (default: wrk when installed)")
    ap.add_argument("--seconds", type=float, default=15, help="duration of each wrk run")
    ap.add_argument("--api-workers", type=int, default=1, help="uvicorn worker processes")
    ap.add_argument(
        "--api-env", action="append", default=[], metavar="NAME=VALUE",
        help="a MIDVIEW_NAME setting of the API, e.g. STATUS_CACHE_S=0 (repeatable)",
    )  # fmt: skip
    ap.add_argument("--json", type=Path, help="also write the figures here (docs/results/service.json)")
    args = ap.parse_args()

    from rich.console import Console
    from rich.table import Table

    console = Console()
    stack = Stack()
    rows: list[tuple[str, str, str]] = []
    figures: dict[str, float] = {}
    try:
        with console.status("starting PostgreSQL, Redis, SeaweedFS, uvicorn"):
            stack.start()
            stack.env.update({f"MIDVIEW_{k}": v for k, _, v in (e.partition("=") for e in args.api_env)})
            base = stack.start_api(args.api_workers)
        from api.bootstrap import create_tenant_with_key
        from shared.db import crud
        from shared.db.session import make_engine, session_scope

        engine = make_engine(stack.env["MIDVIEW_DATABASE_URL"])
        with session_scope(engine) as s:
            key = create_tenant_with_key(s, f"bench-{uuid.uuid4().hex[:8]}")
            tenant_id = crud.get_api_key(s, key).tenant_id
            project = crud.create_project(s, tenant_id, "bench")
            job = crud.create_job(s, project.id)
            project_id, job_id = project.id, job.id
            others = [crud.create_job(s, project.id).id for _ in range(args.clients - 1)]
        engine.dispose()
        headers = {"Authorization": f"Bearer {key}"}

        load = args.load or ("wrk" if shutil.which("wrk") else "httpx")
        with console.status(f"GET latency ({load}), {args.clients} clients"):
            if load == "wrk":
                health = hammer_wrk(base, "/healthz", headers, args.clients, args.seconds)
                jobs = hammer_wrk(base, f"/jobs/{job_id}", headers, args.clients, args.seconds)
                one = hammer_wrk(base, f"/jobs/{job_id}", headers, 1, args.seconds)
                spread = hammer_wrk(base, "/jobs/", headers, args.clients, args.seconds, [job_id, *others])
                figures["status_p99_ms_50_clients_50_jobs"] = spread["p99"]
                rows.append((
                    "GET /jobs/{id} p50 / p99, each client its own job",
                    f"{spread['p50']:.1f} / {spread['p99']:.1f} ms",
                    f"{spread['rps']:.0f} req/s, {args.clients} jobs",
                ))  # fmt: skip
            else:
                health = asyncio.run(hammer(base, "/healthz", headers, args.clients, args.requests))
                jobs = asyncio.run(hammer(base, f"/jobs/{job_id}", headers, args.clients, args.requests))
                one = asyncio.run(hammer(base, f"/jobs/{job_id}", headers, 1, min(args.requests, 500)))
        figures["load_generator"] = load
        rows.append(("GET /jobs/{id} p50 / p99, 1 client", f"{one['p50']:.1f} / {one['p99']:.1f} ms", ""))
        figures["status_p99_ms_50_clients"] = jobs["p99"]
        figures["status_p99_ms_1_client"] = one["p99"]
        figures["status_rps_50_clients"] = jobs["rps"]
        figures["healthz_p99_ms_50_clients"] = health["p99"]
        pauses = gc_pauses(stack.tmp / "uvicorn.log")
        figures["api_gc_pauses_over_20ms"] = len(pauses)
        figures["api_gc_worst_pause_ms"] = max(pauses, default=0.0)
        rows.append(
            (
                "API garbage-collector pauses >= 20 ms",
                str(len(pauses)),
                f"worst {max(pauses, default=0):.0f} ms",
            )
        )
        for name, m in (("GET /healthz", health), ("GET /jobs/{id}", jobs)):
            rows.append((f"{name} p50 / p99", f"{m['p50']:.1f} / {m['p99']:.1f} ms", f"{m['errors']} errors"))
            rows.append((f"{name} throughput", f"{m['rps']:.0f} req/s", f"{args.clients} clients"))
        rows.append((
            "jobs / healthz",
            f"p50 x{jobs['p50'] / health['p50']:.2f}, p99 x{jobs['p99'] / health['p99']:.2f}",
            f"throughput x{jobs['rps'] / health['rps']:.2f}",
        ))  # fmt: skip

        if args.burst:
            with session_scope(make_engine(stack.env["MIDVIEW_DATABASE_URL"])) as s:
                other_key = create_tenant_with_key(s, f"bench-other-{uuid.uuid4().hex[:8]}")
                other_project = crud.create_project(s, crud.get_api_key(s, other_key).tenant_id, "other").id
            paths = {"events": f"/jobs/{job_id}/events", "project": f"/projects/{project_id}",
                     "other": f"/projects/{other_project}"}  # fmt: skip
            with console.status(f"a burst of {args.burst} requests from one key, half event streams"):
                b = asyncio.run(
                    burst(base, headers, {"Authorization": f"Bearer {other_key}"}, paths, args.burst, 5.0)
                )
            figures.update({k: v for k, v in b.items() if k != "burst_answers"})
            figures["burst_answers"] = b["burst_answers"]
            rows.append((
                f"another tenant's reads during a burst of {args.burst} from one key, p99",
                f"{b['burst_other_tenant_p99_ms']:.1f} ms",
                f"healthz p99 {b['burst_healthz_p99_ms']:.1f} ms; 5xx {b['burst_5xx']}; "
                f"answers {b['burst_answers']}",
            ))  # fmt: skip

        if not args.skip_uploads:
            upload_section(console, stack, base, headers, project_id, args, rows, figures)

        if args.skip_workers:
            rows.append(("match_views, 1 / 2 workers", "not measured", "--skip-workers"))
        else:
            try:
                with console.status("tiny job through Celery workers (minutes)"):
                    w = bench_workers(stack, base, headers)
                for n in (1, 2):
                    rows.append((
                        f"match_views, {n} worker process{'es' if n > 1 else ''}",
                        f"{w[n]:.1f} s",
                        f"fresh tiny job, whole job {w[f'job{n}_s']:.1f} s",
                    ))  # fmt: skip
                rows.append(("match_views 2 / 1 workers", f"x{w[2] / w[1]:.2f}", "time ratio (< 1: faster)"))
                figures["match_views_speedup_2_workers"] = w[1] / w[2]
                if w.get("blocks1") and w.get("blocks2"):
                    for n in (1, 2):
                        rows.append((
                            f"train_blocks, {n} worker process{'es' if n > 1 else ''}",
                            f"{w[f'blocks{n}']:.1f} s",
                            f"{w[f'blocks{n}_n']} blocks of {WORKER_OPTIONS['block_steps']} steps",
                        ))  # fmt: skip
                    figures["blocks_speedup_2_workers"] = w["blocks1"] / w["blocks2"]
                    figures["blocks"] = w["blocks1_n"]
            except Exception as e:  # noqa: BLE001 - reported in the table
                rows.append(("match_views, 1 / 2 workers", "not measured", str(e).splitlines()[0][:200]))
    finally:
        stack.stop()

    table = Table(title=f"midview service ({os.cpu_count()} cores)")
    table.add_column("measure")
    table.add_column("value", justify="right")
    table.add_column("notes")
    for row in rows:
        table.add_row(*row)
    console.print(table)
    for note in stack.notes:
        console.print(f"note: {note}")
    if args.json:
        import subprocess

        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout
        doc = {
            "command": "python bench/service.py " + " ".join(sys.argv[1:]),
            "api_env": args.api_env,
            "commit": commit.strip(),
            "cores": os.cpu_count(),
            "clients": args.clients,
            "figures": figures,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
        console.print(f"figures: {args.json}")


if __name__ == "__main__":
    main()
