"""midview's Python client: the REST API (its OpenAPI schema is the contract, checked in the tests),
resumable uploads of survey folders, idempotent submission, the job's event stream, downloads and
campaigns. It depends on httpx only (and PyYAML for YAML manifests), nothing else of midview.

    from client import MidviewClient, submit_survey
    with MidviewClient("https://midview.example.org", api_key) as mv:
        job = submit_survey(mv, Survey("site-7", "aerial/", "ground/", "pos.csv"))
        job = mv.follow(job["id"], on_event=print)
        download_job(mv, job["id"], "results/")
"""

from client.campaign import CampaignReport, Manifest, read_manifest, run_campaign
from client.download import download_job
from client.http import ApiError, MidviewClient
from client.survey import SubmitProgress, Survey, submit_survey
from client.uploads import UploadResult, upload_image

__all__ = [
    "ApiError",
    "CampaignReport",
    "Manifest",
    "MidviewClient",
    "SubmitProgress",
    "Survey",
    "UploadResult",
    "download_job",
    "read_manifest",
    "run_campaign",
    "submit_survey",
    "upload_image",
]
