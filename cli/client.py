"""Client commands against a midview service (client/): submit a survey, list jobs, download results,
run campaigns. The server and key come from --server/--api-key or MIDVIEW_SERVER/MIDVIEW_API_KEY.

    midview submit aerial/ ground/ pos.csv --server https://mv.example.org --out results/
    midview jobs --project site-7
    midview download JOB_ID results/ --only 'combined/gis/*'
    midview campaign submit campaign.csv --concurrency 2
    midview campaign status campaign
    midview campaign retry campaign          # failed jobs again, each from the stage that failed
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer

ServerOption = typer.Option(..., "--server", envvar="MIDVIEW_SERVER", help="the service's base URL")
KeyOption = typer.Option(..., "--api-key", envvar="MIDVIEW_API_KEY", help="API key of your tenant")

campaign_app = typer.Typer(help="Campaigns: many surveys submitted as one batch.", no_args_is_help=True)


def _echo(message: str) -> None:
    typer.echo(message)
    sys.stdout.flush()


@contextmanager
def _client(server: str, api_key: str) -> Iterator[Any]:
    """A MidviewClient; the service's errors and bad input end the command with a message."""
    from client import ApiError, MidviewClient

    try:
        with MidviewClient(server, api_key) as mv:
            yield mv
    except ApiError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    except (FileNotFoundError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None


def parse_options(pairs: list[str], options_file: Path | None) -> dict[str, Any]:
    """Job options from --options-file (JSON) and NAME=VALUE pairs (VALUE parsed as JSON when it is)."""
    options: dict[str, Any] = json.loads(options_file.read_text()) if options_file else {}
    for pair in pairs:
        if "=" not in pair:
            raise typer.BadParameter(f"{pair!r}: expected NAME=VALUE", param_hint="--option")
        name, value = pair.split("=", 1)
        try:
            options[name.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            options[name.replace("-", "_")] = value
    return options


def _outcome(job: dict[str, Any]) -> str:
    out = job.get("outcome") or {}
    reg, tot = out.get("registered") or {}, out.get("images") or {}
    if "ground" in tot:
        return f"ground {reg.get('ground', 0)}/{tot['ground']}"
    return ""


class _Progress:
    """SubmitProgress printing one line per file (logs and pipes) with byte totals."""

    def __init__(self) -> None:
        self.files = self.done = self.bytes = self.total = 0

    def step(self, message: str) -> None:
        _echo(message)

    def uploads_start(self, files: int, total_bytes: int) -> None:
        self.files, self.total, self.done, self.bytes = files, total_bytes, 0, 0
        _echo(f"uploading {files} images ({total_bytes / 1e6:.1f} MB)")

    def part_sent(self, name: str, number: int, count: int, nbytes: int) -> None:
        if count > 1:
            _echo(f"  {name}: part {number}/{count}")

    def file_done(self, result: Any, nbytes: int) -> None:
        self.done += 1
        self.bytes += nbytes
        pct = 100.0 * self.bytes / max(self.total, 1)
        _echo(f"  {result.state} {result.name} ({self.done}/{self.files}, {pct:.0f}%)")


class _BarProgress(_Progress):
    """SubmitProgress drawing a byte progress bar of the uploads (a terminal)."""

    def __init__(self, bars: Any) -> None:
        super().__init__()
        self.bars, self.task = bars, None

    def step(self, message: str) -> None:
        self.bars.console.print(message)

    def uploads_start(self, files: int, total_bytes: int) -> None:
        self.files = files
        self.task = self.bars.add_task(f"uploading {files} images", total=total_bytes)

    def part_sent(self, name: str, number: int, count: int, nbytes: int) -> None:
        self.bars.update(self.task, advance=nbytes, description=name)

    def file_done(self, result: Any, nbytes: int) -> None:
        self.done += 1
        if result.state == "present":  # nothing sent: still counts towards the total
            self.bars.update(self.task, advance=nbytes)
        self.bars.update(self.task, description=f"uploaded {self.done}/{self.files}")


@contextmanager
def _progress() -> Iterator[Any]:
    """A SubmitProgress: a bar on a terminal, one line per event elsewhere (logs, pipes)."""
    if not sys.stdout.isatty():
        yield _Progress()
        return
    from rich.progress import BarColumn, DownloadColumn, Progress, TaskProgressColumn, TextColumn

    with Progress(
        TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(), DownloadColumn()
    ) as bars:
        yield _BarProgress(bars)


def _follow_bar(mv: Any, job_id: str) -> dict[str, Any]:
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn()) as job_bar:
        task = job_bar.add_task(f"job {job_id[:8]}", total=100.0)

        def show(snap: dict[str, Any]) -> None:
            desc = f"job {job_id[:8]} {snap['status']} {snap['stage'] or ''}"
            job_bar.update(task, completed=snap["progress_percent"], description=desc)

        return mv.follow(job_id, on_event=show)


def _follow(mv: Any, job_id: str) -> dict[str, Any]:
    if sys.stdout.isatty():
        return _follow_bar(mv, job_id)
    last: list[Any] = [None]

    def show(snap: dict[str, Any]) -> None:
        state = (snap["status"], snap["stage"], int(snap["progress_percent"]))
        if state != last[0]:
            _echo(f"job {job_id}: {snap['status']} {snap['stage'] or ''} {snap['progress_percent']:.0f}%")
            last[0] = state

    return mv.follow(job_id, on_event=show)


def submit(
    aerial: Path = typer.Argument(..., help="folder of aerial images"),
    ground: Path = typer.Argument(..., help="folder of ground images"),
    pos: Path = typer.Argument(..., help="POS file (docs/formats.md)"),
    server: str = ServerOption,
    api_key: str = KeyOption,
    cameras: Path | None = typer.Option(None, "--cameras", help="cameras.json (intrinsics per set)"),
    project: str | None = typer.Option(None, "--project", help="project name (default: the POS's folder)"),
    key: str | None = typer.Option(
        None, "--key", help="job key: a repeated submission returns that job (default: from the content)"
    ),
    option: list[str] = typer.Option([], "--option", "-o", help="job option NAME=VALUE (repeatable)"),
    options_file: Path | None = typer.Option(None, "--options-file", help="job options as JSON"),
    crs: str | None = typer.Option(None, "--crs", help="the project's output CRS, e.g. EPSG:32633"),
    out: Path | None = typer.Option(None, "--out", help="download the results here at the end"),
    follow: bool = typer.Option(True, "--follow/--no-follow", help="follow the job to its end"),
) -> None:
    """Upload a survey (resuming an interrupted upload), start its job, follow it, download the results."""
    from client import Survey, download_job, submit_survey

    survey = Survey(
        name=project or pos.resolve().parent.name,
        aerial=aerial,
        ground=ground,
        pos=pos,
        cameras=cameras,
        options=parse_options(option, options_file),
        crs=crs,
    )
    with _client(server, api_key) as mv:
        with _progress() as progress:
            job = submit_survey(mv, survey, key=key, progress=progress)
        _echo(f"job {job['id']} (project {survey.name})")
        if not follow:
            return
        job = _follow(mv, job["id"])
        _echo(f"job {job['id']}: {job['status']} {_outcome(job)} {job.get('error') or ''}".rstrip())
        if out is not None and job["status"] == "succeeded":
            files = download_job(mv, job["id"], out)
            _echo(f"downloaded {len(files)} files to {out}")
    if job["status"] != "succeeded":
        raise typer.Exit(1)


def jobs(
    server: str = ServerOption,
    api_key: str = KeyOption,
    project: str | None = typer.Option(None, "--project", help="only this project (name)"),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """The jobs of your projects: status, stage, progress, ground images registered."""
    with _client(server, api_key) as mv:
        rows = []
        for p in mv.projects(project):
            rows += [(p["name"], j) for j in mv.jobs(p["id"])]
    if as_json:
        _echo(json.dumps([{"project": n, **j} for n, j in rows], indent=1))
        return
    for name, j in rows:
        stage, pct = j["current_stage"] or "-", j["progress_percent"]
        _echo(f"{j['id']}  {name:24s} {j['status']:10s} {stage:14s} {pct:5.1f}%  {_outcome(j)}")


def download(
    job_id: str = typer.Argument(..., help="the job"),
    dest: Path = typer.Argument(..., help="folder (files keep their names: combined/gis/cameras.gpkg ...)"),
    server: str = ServerOption,
    api_key: str = KeyOption,
    only: list[str] = typer.Option([], "--only", help="glob of artifact names (repeatable)"),
) -> None:
    """Download a job's results (checked against their sha256; files already there are kept)."""
    from client import download_job

    with _client(server, api_key) as mv:
        files = download_job(mv, job_id, dest, only or None)
    _echo(f"downloaded {len(files)} files to {dest}")


def _show_campaign(c: dict[str, Any]) -> None:
    from client.campaign import CampaignReport

    _echo(CampaignReport(c).summary())
    for j in c.get("jobs", []):
        extra = f"failed at {j['failed_stage']}: {j['error']}" if j.get("failed_stage") else ""
        reg = (
            f"ground {j['registered'].get('ground', 0)}/{j['images'].get('ground', 0)}" if j["images"] else ""
        )
        _echo(f"  {j['project_name']:24s} {j['status']:10s} {j['current_stage'] or '-':14s} {reg} {extra}")


@campaign_app.command("submit")
def campaign_submit(
    manifest: Path = typer.Argument(..., help="CSV or YAML manifest, one survey per row"),
    server: str = ServerOption,
    api_key: str = KeyOption,
    name: str | None = typer.Option(None, "--name", help="campaign name (default: the manifest's)"),
    concurrency: int | None = typer.Option(None, "--concurrency", min=1, help="jobs at once (default 2)"),
    follow: bool = typer.Option(True, "--follow/--no-follow", help="wait until every job has finished"),
    poll: float = typer.Option(2.0, help="seconds between status polls"),
) -> None:
    """Submit a campaign; submitting it again resumes where it stopped."""
    from client import read_manifest, run_campaign

    with _client(server, api_key) as mv:
        m = read_manifest(manifest, name, concurrency)
        _echo(f"campaign {m.name}: {len(m.surveys)} surveys, at most {m.max_concurrent} jobs at once")
        report = run_campaign(mv, m, _Progress(), follow=follow, poll_s=poll, on_status=_show_campaign)
    _echo(report.summary())
    if follow and not report.all_succeeded():
        _echo(f"retry the failed jobs from their failed stage: midview campaign retry {m.name}")
        raise typer.Exit(1)


@campaign_app.command("status")
def campaign_status(
    campaign: str = typer.Argument(..., help="campaign name or id"),
    server: str = ServerOption,
    api_key: str = KeyOption,
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """Jobs by state, ground images registered in all, and each survey's job."""
    from client.campaign import find_campaign

    with _client(server, api_key) as mv:
        c = mv.campaign(find_campaign(mv, campaign)["id"])
    if as_json:
        _echo(json.dumps(c, indent=1))
    else:
        _show_campaign(c)


@campaign_app.command("retry")
def campaign_retry(
    campaign: str = typer.Argument(..., help="campaign name or id"),
    server: str = ServerOption,
    api_key: str = KeyOption,
    from_start: bool = typer.Option(False, "--from-start", help="rerun from the first stage"),
    follow: bool = typer.Option(True, "--follow/--no-follow", help="wait until every job has finished"),
    poll: float = typer.Option(2.0, help="seconds between status polls"),
) -> None:
    """Rerun the campaign's failed jobs, each from the stage that failed, as slots free up."""
    from client.campaign import find_campaign, retry_campaign

    with _client(server, api_key) as mv:
        cid = find_campaign(mv, campaign)["id"]
        rerun, report = retry_campaign(
            mv, cid, from_failed_stage=not from_start, follow=follow, poll_s=poll, on_status=_show_campaign
        )
    for j in rerun:
        _echo(f"rerun {j['project_name']} (job {j['id']}, attempt {j['attempt']})")
    _echo(report.summary())
    if follow and not report.all_succeeded():
        raise typer.Exit(1)
