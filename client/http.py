"""MidviewClient: one typed method per API route the client uses (ENDPOINTS lists them; the tests check
each against the service's OpenAPI schema), retries of what is safe to retry, and errors that say what
the service answered."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypedDict
from urllib.parse import urlsplit

import httpx

FINAL_STATUSES = frozenset({"succeeded", "failed", "cancelled"})
RETRY_STATUSES = frozenset({429, 502, 503, 504})

# (method, path) of every route the client calls: its contract with the service's OpenAPI schema
ENDPOINTS: tuple[tuple[str, str], ...] = (
    ("GET", "/projects"),
    ("POST", "/projects"),
    ("GET", "/projects/{project_id}"),
    ("GET", "/projects/{project_id}/images"),
    ("GET", "/projects/{project_id}/images/{image_set}/{filename}"),
    ("GET", "/projects/{project_id}/uploads"),
    ("POST", "/projects/{project_id}/uploads"),
    ("GET", "/projects/{project_id}/uploads/{upload_id}/parts"),
    ("GET", "/projects/{project_id}/uploads/{upload_id}/parts/{part_number}"),
    ("PUT", "/projects/{project_id}/uploads/{upload_id}/parts/{part_number}"),
    ("POST", "/projects/{project_id}/uploads/{upload_id}/complete"),
    ("DELETE", "/projects/{project_id}/uploads/{upload_id}"),
    ("POST", "/projects/{project_id}/pos"),
    ("PUT", "/projects/{project_id}/cameras"),
    ("GET", "/projects/{project_id}/jobs"),
    ("POST", "/projects/{project_id}/jobs"),
    ("GET", "/jobs/{job_id}"),
    ("GET", "/jobs/{job_id}/events"),
    ("POST", "/jobs/{job_id}/cancel"),
    ("POST", "/jobs/{job_id}/rerun"),
    ("GET", "/jobs/{job_id}/artifacts"),
    ("GET", "/campaigns"),
    ("POST", "/campaigns"),
    ("GET", "/campaigns/{campaign_id}"),
    ("POST", "/campaigns/{campaign_id}/retry"),
)


class Project(TypedDict):
    id: str
    name: str
    crs: str | None


class Image(TypedDict):
    id: str
    name: str
    image_set: str
    sha256: str
    size_bytes: int


class Upload(TypedDict, total=False):
    id: str
    name: str
    size: int
    sha256: str | None
    part_size: int
    part_count: int
    parts_via: str
    state: str
    part_urls: list[dict[str, Any]] | None  # with the start: where to PUT each part (presigned)


class Job(TypedDict, total=False):
    id: str
    project_id: str
    status: str
    current_stage: str | None
    progress: float
    progress_percent: float
    options: dict[str, Any]
    metrics: dict[str, Any]
    outcome: dict[str, Any] | None
    error: str | None
    attempt: int
    key: str | None
    campaign_id: str | None
    stages: list[dict[str, Any]]


class Artifact(TypedDict):
    id: str
    name: str
    kind: str
    size_bytes: int | None
    sha256: str | None
    download_url: str | None


class Campaign(TypedDict, total=False):
    id: str
    name: str
    max_concurrent: int
    jobs_by_status: dict[str, int]
    active: int
    ground_registered: int
    ground_images: int
    done: bool
    jobs: list[dict[str, Any]]


class ApiError(Exception):
    """The service answered with an error status: the method, the path, the status and its reason."""

    def __init__(self, status: int, method: str, path: str, detail: Any) -> None:
        self.status, self.method, self.path, self.detail = status, method, path, detail
        super().__init__(f"{method} {path}: HTTP {status}: {_detail_text(detail)}")


def _detail_text(detail: Any) -> str:
    if isinstance(detail, dict):
        msg = detail.get("message") or json.dumps(detail)[:500]
        errors = detail.get("errors")
        return f"{msg}: {'; '.join(map(str, errors[:5]))}" if errors else str(msg)
    return str(detail)[:1000]


def _error(r: httpx.Response) -> ApiError:
    try:
        detail = r.json().get("detail", r.text)
    except (ValueError, AttributeError):
        detail = r.text
    return ApiError(r.status_code, r.request.method, r.request.url.path, detail)


class MidviewClient:
    """The midview REST API at `server` with an API key. `http` may be given (an httpx.Client whose
    base_url is the server, e.g. a FastAPI TestClient); requests that fail before reaching the service,
    and 429/502/503/504 answers to requests that are safe to repeat, are retried with backoff."""

    def __init__(
        self,
        server: str,
        api_key: str,
        *,
        timeout: float = 60.0,
        retries: int = 4,
        http: httpx.Client | None = None,
    ) -> None:
        self.server = server.rstrip("/")
        self.retries = retries
        self._auth = {"Authorization": f"Bearer {api_key}"}
        self._http = http or httpx.Client(base_url=self.server, timeout=timeout)
        self._own_http = http is None
        self._plain = httpx.Client(timeout=timeout)  # presigned storage URLs: no API key sent there

    def __enter__(self) -> MidviewClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._own_http:
            self._http.close()
        self._plain.close()

    # -- requests ---------------------------------------------------------------------------------
    def _is_api(self, url: str) -> bool:
        """Whether an absolute URL points at the API (send the key) rather than at the storage."""
        u, base = urlsplit(url), urlsplit(str(self._http.base_url))
        return (u.scheme, u.netloc) == (base.scheme, base.netloc)

    def request(self, method: str, path: str, *, ok: tuple[int, ...] = (200,), **kw: Any) -> httpx.Response:
        """One API request; ApiError unless the status is in ok. POSTs are retried only when the request
        never reached the service (connection refused), other methods also on 429/502/503/504."""
        idempotent = method in ("GET", "PUT", "DELETE", "HEAD")
        for attempt in range(self.retries + 1):
            try:
                r = self._http.request(method, path, headers=self._auth, **kw)
            except (httpx.ConnectError, httpx.ConnectTimeout) as e:
                if attempt == self.retries:
                    raise ApiError(0, method, path, f"cannot reach the service: {e}") from e
                time.sleep(min(2.0**attempt, 10.0))
                continue
            if (
                r.status_code in RETRY_STATUSES
                and (idempotent or r.status_code == 429)
                and attempt < self.retries
            ):
                wait = float(r.headers.get("Retry-After", 0) or 0) or min(2.0**attempt, 10.0)
                time.sleep(min(wait, 30.0))
                continue
            if r.status_code not in ok:
                raise _error(r)
            return r
        raise AssertionError("unreachable")

    def _json(self, method: str, path: str, ok: tuple[int, ...] = (200,), **kw: Any) -> Any:
        return self.request(method, path, ok=ok, **kw).json()

    # -- projects, images, POS, cameras -------------------------------------------------------------
    def projects(self, name: str | None = None) -> list[Project]:
        return self._json("GET", "/projects", params={"name": name} if name else None)

    def create_project(self, name: str, crs: str | None = None, description: str | None = None) -> Project:
        body = {k: v for k, v in {"name": name, "crs": crs, "description": description}.items() if v}
        return self._json("POST", "/projects", ok=(201,), json=body)

    def ensure_project(self, name: str, crs: str | None = None) -> Project:
        """The tenant's project of this name, created when there is none."""
        found = self.projects(name)
        if found:
            return found[0]
        try:
            return self.create_project(name, crs=crs)
        except ApiError as e:  # created meanwhile (a concurrent or repeated submission)
            if e.status != 409 or not (found := self.projects(name)):
                raise
            return found[0]

    def project(self, project_id: str) -> dict[str, Any]:
        return self._json("GET", f"/projects/{project_id}")

    def images(self, project_id: str, image_set: str | None = None) -> list[Image]:
        params = {"set": image_set} if image_set else None
        return self._json("GET", f"/projects/{project_id}/images", params=params)

    def upload_pos(self, project_id: str, path: Path) -> dict[str, Any]:
        files = {"file": (Path(path).name, Path(path).read_bytes())}
        return self._json("POST", f"/projects/{project_id}/pos", files=files)

    def put_cameras(self, project_id: str, cameras: dict[str, Any]) -> dict[str, Any]:
        return self._json("PUT", f"/projects/{project_id}/cameras", json=cameras)

    # -- multipart uploads --------------------------------------------------------------------------
    def uploads(self, project_id: str) -> list[Upload]:
        return self._json("GET", f"/projects/{project_id}/uploads")

    def create_upload(self, project_id: str, name: str, size: int, sha256: str | None = None) -> Upload:
        body = {"name": name, "size": size, **({"sha256": sha256} if sha256 else {})}
        return self._json("POST", f"/projects/{project_id}/uploads", ok=(201,), json=body)

    def upload_parts(self, project_id: str, upload_id: str) -> dict[str, Any]:
        return self._json("GET", f"/projects/{project_id}/uploads/{upload_id}/parts")

    def put_part(
        self, project_id: str, upload_id: str, number: int, data: bytes, where: dict[str, Any] | None = None
    ) -> str:
        """Send part `number` where the service says (presigned storage URL or the API); its ETag.
        `where`: the part's URL given with the upload's start (else asked for); an expired one (403) is
        asked for again."""
        if where is None:
            where = self._json("GET", f"/projects/{project_id}/uploads/{upload_id}/parts/{number}")
        url = where["url"]
        if self._is_api(url) or where["needs_auth"]:
            r = self.request("PUT", url, content=data)
            return r.json()["etag"]
        try:
            return self._put_presigned(url, data)
        except ApiError as e:
            if e.status != 403:
                raise
        fresh = self._json("GET", f"/projects/{project_id}/uploads/{upload_id}/parts/{number}")
        return self._put_presigned(fresh["url"], data)

    def _put_presigned(self, url: str, data: bytes) -> str:
        """PUT to a presigned storage URL, retried on transient errors; the part's ETag."""
        for attempt in range(self.retries + 1):
            try:
                r = self._plain.put(url, content=data)
            except httpx.TransportError as e:
                if attempt == self.retries:
                    raise ApiError(0, "PUT", urlsplit(url).path, f"cannot reach the storage: {e}") from e
                time.sleep(min(2.0**attempt, 10.0))
                continue
            if r.status_code == 200:
                return r.headers["ETag"]
            if r.status_code not in RETRY_STATUSES or attempt == self.retries:
                raise ApiError(r.status_code, "PUT", urlsplit(url).path, r.text[:500])
        raise AssertionError("unreachable")

    def complete_upload(
        self,
        project_id: str,
        upload_id: str,
        wait: bool = True,
        parts: list[tuple[int, str]] | None = None,
        sha256: str | None = None,
    ) -> dict[str, Any]:
        """Assemble the parts (those given with their ETags, else those the storage lists): the image
        row (wait), or with wait false the upload, `verifying` (its check runs on the service; see
        wait_uploads_checked). sha256: the file's, when the start did not give it."""
        path = f"/projects/{project_id}/uploads/{upload_id}/complete"
        body: dict[str, Any] = {"wait": wait}
        if parts is not None:
            body["parts"] = [{"part_number": n, "etag": etag} for n, etag in parts]
        if sha256 is not None:
            body["sha256"] = sha256
        return self._json("POST", path, ok=(201, 202), json=body)

    def wait_uploads_checked(self, project_id: str, timeout_s: float = 600.0, poll_s: float = 0.2) -> None:
        """Wait until the service has checked every upload completed without waiting; ValueError naming
        those it rejected and why, TimeoutError after timeout_s."""
        deadline = time.monotonic() + timeout_s
        while True:
            ups = self.uploads(project_id)
            rejected = [f"{u['name']}: {u.get('error')}" for u in ups if u.get("state") == "rejected"]
            if rejected:
                raise ValueError(
                    f"{len(rejected)} image(s) failed the service's check: {'; '.join(rejected[:5])}"
                )
            if not any(u.get("state") == "verifying" for u in ups):
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"uploads of project {project_id} still being checked after {timeout_s} s")
            time.sleep(poll_s)

    def abort_upload(self, project_id: str, upload_id: str) -> None:
        self.request("DELETE", f"/projects/{project_id}/uploads/{upload_id}", ok=(204, 404))

    # -- jobs ---------------------------------------------------------------------------------------
    def create_job(
        self,
        project_id: str,
        options: dict[str, Any] | None = None,
        key: str | None = None,
        campaign_id: str | None = None,
    ) -> Job:
        """Queue a job; with a key, a repeat returns the job made the first time."""
        body: dict[str, Any] = {"options": options or {}}
        if key:
            body["key"] = key
        if campaign_id:
            body["campaign_id"] = campaign_id
        return self._json("POST", f"/projects/{project_id}/jobs", ok=(200, 201), json=body)

    def jobs(self, project_id: str, key: str | None = None) -> list[Job]:
        return self._json("GET", f"/projects/{project_id}/jobs", params={"key": key} if key else None)

    def job(self, job_id: str) -> Job:
        return self._json("GET", f"/jobs/{job_id}")

    def cancel(self, job_id: str) -> Job:
        return self._json("POST", f"/jobs/{job_id}/cancel")

    def rerun(self, job_id: str, from_stage: str | None = None, force: bool = False) -> Job:
        """Run a finished job again from `from_stage` (None: the start); `force`: even the stages whose
        inputs are unchanged (otherwise skipped as up to date)."""
        return self._json("POST", f"/jobs/{job_id}/rerun", json={"from_stage": from_stage, "force": force})

    def events(self, job_id: str) -> Iterator[tuple[str, dict[str, Any]]]:
        """The job's server-sent events as (event, data) until the stream ends."""
        with self._http.stream("GET", f"/jobs/{job_id}/events", headers=self._auth, timeout=None) as r:
            if r.status_code != 200:
                r.read()
                raise _error(r)
            event, data = None, None
            for line in r.iter_lines():
                if line.startswith("event: "):
                    event = line[7:]
                elif line.startswith("data: "):
                    data = json.loads(line[6:])
                elif line == "" and event is not None:
                    yield event, data or {}
                    event, data = None, None

    def follow(
        self,
        job_id: str,
        on_event: Callable[[dict[str, Any]], None] | None = None,
        timeout_s: float | None = None,
    ) -> Job:
        """Follow the job's event stream to its end (reconnecting when the stream drops); the final job.
        on_event gets every progress snapshot."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            try:
                for event, data in self.events(job_id):
                    if event == "progress" and on_event is not None:
                        on_event(data)
                    if event in ("end", "error"):
                        return self.job(job_id)
            except (httpx.TransportError, httpx.StreamError):
                pass  # dropped: reconnect (the first event of a new stream is the job's current state)
            job = self.job(job_id)
            if job["status"] in FINAL_STATUSES:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} is {job['status']} after {timeout_s} s")
            time.sleep(1.0)

    # -- artifacts ----------------------------------------------------------------------------------
    def artifacts(self, job_id: str) -> list[Artifact]:
        return self._json("GET", f"/jobs/{job_id}/artifacts")

    def download_to(self, url: str, dest: Path) -> Path:
        """Stream a download URL (presigned storage URL, or the API's route with the key) to dest."""
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(dest.name + ".part")
        http, headers = (self._http, self._auth) if self._is_api(url) else (self._plain, {})
        with http.stream("GET", url, headers=headers) as r:
            if r.status_code != 200:
                r.read()
                raise _error(r)
            with open(tmp, "wb") as f:
                for chunk in r.iter_bytes(1 << 20):
                    f.write(chunk)
        tmp.replace(dest)
        return dest

    # -- campaigns ----------------------------------------------------------------------------------
    def campaigns(self) -> list[Campaign]:
        return self._json("GET", "/campaigns")

    def create_campaign(self, name: str, max_concurrent: int = 2) -> Campaign:
        """The campaign of this name (created, or the one made before with the same limit)."""
        body = {"name": name, "max_concurrent": max_concurrent}
        return self._json("POST", "/campaigns", ok=(200, 201), json=body)

    def campaign(self, campaign_id: str) -> Campaign:
        return self._json("GET", f"/campaigns/{campaign_id}")

    def retry_campaign(
        self, campaign_id: str, from_failed_stage: bool = True, limit: int | None = None
    ) -> dict[str, Any]:
        body: dict[str, Any] = {"from_failed_stage": from_failed_stage}
        if limit is not None:
            body["limit"] = limit
        return self._json("POST", f"/campaigns/{campaign_id}/retry", json=body)
