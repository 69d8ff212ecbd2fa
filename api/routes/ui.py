"""The web dashboard: static files (api/ui/) served at /ui/, and / sending browsers there. The page
talks to the same REST API with the user's API key; it needs no server of its own."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

UI_DIR = Path(__file__).resolve().parents[1] / "ui"

router = APIRouter(tags=["dashboard"])


@router.get("/", include_in_schema=False)
def root() -> RedirectResponse:
    return RedirectResponse("/ui/")


def mount_ui(app: FastAPI) -> None:
    """Serve the dashboard's files at /ui/ (index.html at /ui/)."""
    app.mount("/ui", StaticFiles(directory=UI_DIR, html=True), name="ui")
