"""Routers of the REST API, one module per resource."""

from api.routes import (
    artifacts,
    cameras,
    campaigns,
    health,
    images,
    jobs,
    pos,
    projects,
    ui,
    uploads,
    webhooks,
)

ROUTERS = [
    health.router,
    projects.router,
    images.router,
    uploads.router,
    pos.router,
    cameras.router,
    jobs.router,
    campaigns.router,
    artifacts.router,
    webhooks.router,
    ui.router,
]

__all__ = ["ROUTERS"]
