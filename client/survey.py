"""Submit one survey (a folder of aerial images, one of ground images, a POS file, optionally a
cameras.json and job options): project, resumable uploads, POS, intrinsics, the job. Idempotent: the
job key (the client's, or one derived from the survey's content and options) makes a repeated or
resumed submission find its job instead of making another."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from client.http import Job, MidviewClient
from client.uploads import UploadResult, upload_image

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


@dataclass
class Survey:
    """What one job registers; `name` is its project's name."""

    name: str
    aerial: Path
    ground: Path | None
    pos: Path
    cameras: Path | None = None
    options: dict[str, Any] = field(default_factory=dict)
    crs: str | None = None

    def images(self) -> list[tuple[str, Path]]:
        """[(SET/FILE, path)] of the survey's image files, sorted."""
        out = []
        for image_set, folder in (("aerial", self.aerial), ("ground", self.ground)):
            if folder is None:
                continue
            if not Path(folder).is_dir():
                raise FileNotFoundError(f"{image_set} images: {folder} is not a folder")
            files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not files:
                raise FileNotFoundError(
                    f"{image_set} images: no {'/'.join(IMAGE_SUFFIXES)} files in {folder}"
                )
            out += [(f"{image_set}/{p.name}", p) for p in files]
        return out

    def check(self) -> None:
        """FileNotFoundError naming what is missing: an image folder, its images, the POS, cameras.json."""
        self.images()
        for what, path in (("POS file", self.pos), ("cameras.json", self.cameras)):
            if path is not None and not Path(path).is_file():
                raise FileNotFoundError(f"{what} {path} not found")

    def default_key(self) -> str:
        """A job key from the survey's content: the same folders, POS and options give the same key."""
        h = hashlib.sha256(self.name.encode())
        for name, path in self.images():
            h.update(f"{name}:{path.stat().st_size}:{int(path.stat().st_mtime)}".encode())
        for extra in (self.pos, self.cameras):
            if extra is not None:
                h.update(Path(extra).read_bytes())
        h.update(json.dumps(self.options, sort_keys=True).encode())
        return f"auto-{h.hexdigest()[:32]}"


class SubmitProgress:
    """Callbacks of a submission (all optional; the CLI draws progress bars with them)."""

    def step(self, message: str) -> None: ...

    def uploads_start(self, files: int, total_bytes: int) -> None: ...

    def part_sent(self, name: str, number: int, count: int, nbytes: int) -> None: ...

    def file_done(self, result: UploadResult, nbytes: int) -> None: ...


def upload_survey_images(
    mv: MidviewClient, project_id: str, survey: Survey, progress: SubmitProgress
) -> list[UploadResult]:
    """Upload the survey's images that the project lacks, resuming unfinished uploads."""
    files = survey.images()
    stored = {im["name"]: im["sha256"] for im in mv.images(project_id)}
    pending = {u["name"]: u for u in mv.uploads(project_id)}
    progress.uploads_start(len(files), sum(p.stat().st_size for _, p in files))
    results = []
    for name, path in files:  # each image checked by the service while the next one travels
        res = upload_image(
            mv, project_id, name, path, stored, pending, on_part=progress.part_sent, wait=False
        )
        progress.file_done(res, path.stat().st_size)
        results.append(res)
    progress.step("waiting for the service to check the images")
    mv.wait_uploads_checked(project_id)
    return results


def submit_survey(
    mv: MidviewClient,
    survey: Survey,
    key: str | None = None,
    campaign_id: str | None = None,
    progress: SubmitProgress | None = None,
    before_job: Callable[[], None] | None = None,
) -> Job:
    """The survey's job: found by its key when submitted before, else made after uploading what the
    project lacks (images, POS rows, cameras.json); before_job runs just before the job is created (a
    campaign waits there for a free slot)."""
    progress = progress or SubmitProgress()
    survey.check()  # bad local input fails before any request
    key = key or survey.default_key()
    project = mv.ensure_project(survey.name, crs=survey.crs)
    found = mv.jobs(project["id"], key=key)
    if found:
        progress.step(f"{survey.name}: job {found[0]['id']} exists with key {key}")
        return found[0]
    upload_survey_images(mv, project["id"], survey, progress)
    progress.step(f"{survey.name}: POS from {survey.pos}")
    pos = mv.upload_pos(project["id"], survey.pos)
    for warning in pos.get("warnings", [])[:10]:
        progress.step(f"{survey.name}: POS: {warning}")
    if survey.cameras is not None:
        mv.put_cameras(project["id"], json.loads(Path(survey.cameras).read_text()))
    if before_job is not None:
        before_job()
    job = mv.create_job(project["id"], survey.options, key=key, campaign_id=campaign_id)
    progress.step(f"{survey.name}: job {job['id']} {job['status']} (key {key})")
    return job
