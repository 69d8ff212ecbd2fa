"""Webhooks of the tenant: job.succeeded / job.failed events POSTed signed (see shared/webhooks.py)."""

from __future__ import annotations

from typing import Annotated

import sqlalchemy as sa
from fastapi import APIRouter, HTTPException, Query, Response, status
from sqlalchemy.orm import Session

from api.deps import SessionDep, SettingsDep, TenantDep
from api.schemas import DeliveryOut, WebhookCreate, WebhookCreated, WebhookOut
from shared import netguard
from shared.db.models import Webhook, WebhookDelivery
from shared.webhooks import new_secret

router = APIRouter(prefix="/webhooks", tags=["webhooks"])


def _webhook(session: Session, tenant_id: str, webhook_id: str) -> Webhook:
    hook = session.get(Webhook, webhook_id)
    if hook is None or hook.tenant_id != tenant_id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"webhook {webhook_id} not found")
    return hook


@router.post("", status_code=status.HTTP_201_CREATED, response_model=WebhookCreated)
def create_webhook(
    body: WebhookCreate, tenant: TenantDep, session: SessionDep, settings: SettingsDep
) -> WebhookCreated:
    """Register a URL for events; the response holds the signing secret, shown only this once.

    422 for a URL that names a non-public address (in any encoding), a local name, or a host name that
    resolves to a non-public address now; host names are resolved and checked again at every delivery."""
    try:
        netguard.check_registration(str(body.url), netguard.parse_networks(settings.webhook_allow_networks))
    except netguard.BlockedURL as e:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"webhook url {e}") from e
    hook = Webhook(
        tenant_id=tenant.id, url=str(body.url), secret=new_secret(), events=sorted(set(body.events))
    )
    session.add(hook)
    session.commit()
    return WebhookCreated(**WebhookOut.model_validate(hook).model_dump(), secret=hook.secret)


@router.get("", response_model=list[WebhookOut])
def list_webhooks(tenant: TenantDep, session: SessionDep) -> list[WebhookOut]:
    hooks = session.scalars(
        sa.select(Webhook).where(Webhook.tenant_id == tenant.id).order_by(Webhook.created_at)
    )
    return [WebhookOut.model_validate(h) for h in hooks]


@router.get("/{webhook_id}", response_model=WebhookOut)
def get_webhook(webhook_id: str, tenant: TenantDep, session: SessionDep) -> WebhookOut:
    return WebhookOut.model_validate(_webhook(session, tenant.id, webhook_id))


@router.delete("/{webhook_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_webhook(webhook_id: str, tenant: TenantDep, session: SessionDep) -> Response:
    """Delete the webhook and its delivery history (pending deliveries are dropped)."""
    session.delete(_webhook(session, tenant.id, webhook_id))
    session.commit()
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{webhook_id}/deliveries", response_model=list[DeliveryOut])
def list_deliveries(
    webhook_id: str,
    tenant: TenantDep,
    session: SessionDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[DeliveryOut]:
    """The newest deliveries first, with attempts, status and the last error."""
    hook = _webhook(session, tenant.id, webhook_id)
    rows = session.scalars(
        sa.select(WebhookDelivery)
        .where(WebhookDelivery.webhook_id == hook.id)
        .order_by(WebhookDelivery.created_at.desc())
        .limit(limit)
    )
    return [DeliveryOut.model_validate(d) for d in rows]
