"""Campaigns: a manifest of surveys (CSV or YAML, one survey per row) submitted as one campaign with a
concurrency limit. Surveys are uploaded one after the other while earlier jobs run; a survey's job is
created once fewer than max_concurrent jobs of the campaign are queued or running. Submitting the same
manifest again resumes: campaign, projects and jobs are found by name and key.

CSV columns: name, aerial, ground, pos, and optionally cameras, crs, options (a JSON object).
YAML: {name, max_concurrent, options (defaults for every survey), surveys: [{name, aerial, ...}]}.
Paths are relative to the manifest's folder.
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from client.http import Campaign, MidviewClient
from client.survey import SubmitProgress, Survey, submit_survey

SURVEY_FIELDS = {"name", "aerial", "ground", "pos", "cameras", "crs", "options"}


@dataclass
class Manifest:
    name: str
    max_concurrent: int = 2
    surveys: list[Survey] = field(default_factory=list)


def _survey(row: dict[str, Any], root: Path, defaults: dict[str, Any], where: str) -> Survey:
    unknown = set(row) - SURVEY_FIELDS
    if unknown:
        raise ValueError(f"{where}: unknown column(s) {sorted(unknown)}; expected {sorted(SURVEY_FIELDS)}")
    missing = [k for k in ("name", "aerial", "pos") if not row.get(k)]
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    options = row.get("options") or {}
    if isinstance(options, str):
        try:
            options = json.loads(options)
        except json.JSONDecodeError as e:
            raise ValueError(f"{where}: options is not a JSON object: {e}") from None
    if not isinstance(options, dict):
        raise ValueError(f"{where}: options must be an object")

    def path(key: str) -> Path | None:
        return (root / str(row[key])).resolve() if row.get(key) else None

    return Survey(
        name=str(row["name"]),
        aerial=path("aerial"),  # type: ignore[arg-type]
        ground=path("ground"),
        pos=path("pos"),  # type: ignore[arg-type]
        cameras=path("cameras"),
        options={**defaults, **options},
        crs=row.get("crs") or None,
    )


def read_manifest(path: Path, name: str | None = None, max_concurrent: int | None = None) -> Manifest:
    """The campaign of a CSV or YAML manifest; name and max_concurrent override the file's."""
    path = Path(path)
    root = path.parent
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        doc = yaml.safe_load(path.read_text()) or {}
        if not isinstance(doc, dict) or not isinstance(doc.get("surveys"), list):
            raise ValueError(f"{path}: expected a mapping with a list `surveys`")
        defaults = doc.get("options") or {}
        rows = doc["surveys"]
        file_name, file_limit = doc.get("name"), doc.get("max_concurrent")
    else:
        with open(path, newline="") as f:
            rows = [{k: v for k, v in r.items() if v not in (None, "")} for r in csv.DictReader(f)]
        defaults, file_name, file_limit = {}, None, None
    surveys = [_survey(r, root, defaults, f"{path.name} survey {i + 1}") for i, r in enumerate(rows)]
    if not surveys:
        raise ValueError(f"{path}: no surveys")
    names = [s.name for s in surveys]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: survey names must be unique (each is a project)")
    return Manifest(
        name=name or file_name or path.stem,
        max_concurrent=int(max_concurrent or file_limit or 2),
        surveys=surveys,
    )


@dataclass
class CampaignReport:
    campaign: Campaign

    def all_succeeded(self) -> bool:
        return self.campaign.get("jobs_by_status", {}).get("succeeded", 0) == len(
            self.campaign.get("jobs", [])
        )

    def summary(self) -> str:
        c = self.campaign
        states = ", ".join(f"{n} {s}" for s, n in sorted(c.get("jobs_by_status", {}).items()))
        return (
            f"campaign {c['name']}: {states or 'no jobs'}; ground images registered "
            f"{c.get('ground_registered', 0)}/{c.get('ground_images', 0)}"
        )


def wait_for_slot(mv: MidviewClient, campaign_id: str, poll_s: float) -> None:
    """Block while the campaign has max_concurrent jobs queued or running."""
    while True:
        c = mv.campaign(campaign_id)
        if c["active"] < c["max_concurrent"]:
            return
        time.sleep(poll_s)


def wait_until_done(
    mv: MidviewClient, campaign_id: str, poll_s: float, on_status: Callable[[Campaign], None] | None = None
) -> Campaign:
    last = None
    while True:
        c = mv.campaign(campaign_id)
        state = (c["jobs_by_status"], [(j["status"], j["current_stage"]) for j in c["jobs"]])
        if on_status is not None and state != last:
            on_status(c)
        last = state
        if c["done"]:
            return c
        time.sleep(poll_s)


def run_campaign(
    mv: MidviewClient,
    manifest: Manifest,
    progress: SubmitProgress | None = None,
    follow: bool = True,
    poll_s: float = 2.0,
    on_status: Callable[[Campaign], None] | None = None,
) -> CampaignReport:
    """Submit every survey of the manifest into its campaign, keeping to its concurrency limit; with
    follow, wait until every job has finished."""
    campaign = mv.create_campaign(manifest.name, manifest.max_concurrent)
    for survey in manifest.surveys:
        submit_survey(
            mv,
            survey,
            campaign_id=campaign["id"],
            progress=progress,
            before_job=lambda: wait_for_slot(mv, campaign["id"], poll_s),
        )
    if follow:
        return CampaignReport(wait_until_done(mv, campaign["id"], poll_s, on_status))
    return CampaignReport(mv.campaign(campaign["id"]))


def retry_campaign(
    mv: MidviewClient,
    campaign_id: str,
    from_failed_stage: bool = True,
    follow: bool = True,
    poll_s: float = 2.0,
    on_status: Callable[[Campaign], None] | None = None,
) -> tuple[list[dict[str, Any]], CampaignReport]:
    """Rerun the campaign's failed jobs (from their failed stage), as slots free up; with follow, until
    every job has finished. ([jobs rerun], report)."""
    rerun: list[dict[str, Any]] = []
    while True:
        r = mv.retry_campaign(campaign_id, from_failed_stage=from_failed_stage)
        rerun += r["rerun"]
        if not r["waiting"] or not follow:
            break
        time.sleep(poll_s)
    if follow:
        return rerun, CampaignReport(wait_until_done(mv, campaign_id, poll_s, on_status))
    return rerun, CampaignReport(mv.campaign(campaign_id))


def find_campaign(mv: MidviewClient, name_or_id: str) -> Campaign:
    """A campaign by id or by name."""
    for c in mv.campaigns():
        if name_or_id in (c["id"], c["name"]):
            return c
    raise ValueError(f"no campaign {name_or_id!r}")
