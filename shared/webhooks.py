"""Webhook deliveries: queue an event for a tenant's webhooks, POST it signed, retry with back-off.

Workers call `enqueue_job_event(session, job)` when a job succeeds or fails, and the worker beat calls
`deliver_due(session)` periodically (then commits). Every delivery is a row of webhook_deliveries.

Each request is a POST of a JSON body `{"id", "event", "created_at", "data"}` (`id` is the delivery id,
the same on every retry, for de-duplication) with the headers

    X-Midview-Event: job.succeeded
    X-Midview-Delivery: <delivery id>
    X-Midview-Timestamp: <unix seconds>
    X-Midview-Signature: sha256=<hex HMAC-SHA256(secret, "<timestamp>." + body)>

The timestamp is part of the signed message so that a captured request cannot be replayed later:
receivers check the HMAC (verify_signature) and that the timestamp is recent. Any 2xx answer is a
success; anything else (or no answer) is retried after base_delay_s * 2**(attempt - 1), capped at
max_delay_s, until max_attempts, when the delivery is marked failed. Redirects are not followed, and
the receiver's answer is recorded by its status code only (never its body).

The URL's host is resolved at each delivery and refused, before any connection, when it is not a
public address (shared.netguard: loopback, private, link-local, multicast, reserved ..., unless the
operator's `webhook_allow_networks` admits it); the request goes to the address that was checked.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import secrets
from datetime import datetime, timedelta
from typing import Any

import httpx
import sqlalchemy as sa
from sqlalchemy.orm import Session

from shared import netguard
from shared.config import get_settings
from shared.db.models import DeliveryStatus, Job, JobStatus, Webhook, WebhookDelivery, utcnow

log = logging.getLogger("midview.webhooks")

EVENTS = ("job.succeeded", "job.failed")
SIGNATURE_HEADER = "X-Midview-Signature"
TIMESTAMP_HEADER = "X-Midview-Timestamp"
EVENT_HEADER = "X-Midview-Event"
DELIVERY_HEADER = "X-Midview-Delivery"

MAX_ATTEMPTS = 8
BASE_DELAY_S = 30.0
MAX_DELAY_S = 3600.0
TIMEOUT_S = 10.0


def new_secret() -> str:
    return "whsec_" + secrets.token_urlsafe(32)


def sign(secret: str, timestamp: str, body: bytes) -> str:
    """The X-Midview-Signature value of a body sent at timestamp."""
    mac = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def verify_signature(
    secret: str,
    body: bytes,
    timestamp: str,
    signature: str,
    tolerance_s: float = 300.0,
    now: datetime | None = None,
) -> bool:
    """What a receiver checks: the signature matches and the timestamp is within tolerance_s of now."""
    try:
        sent = float(timestamp)
    except ValueError:
        return False
    if abs((now or utcnow()).timestamp() - sent) > tolerance_s:
        return False
    return hmac.compare_digest(sign(secret, timestamp, body), signature)


def backoff_s(attempts: int, base_delay_s: float = BASE_DELAY_S, max_delay_s: float = MAX_DELAY_S) -> float:
    """Delay before the next try after `attempts` failed ones."""
    return min(max_delay_s, base_delay_s * 2 ** max(0, attempts - 1))


def job_event(job: Job) -> str | None:
    return {JobStatus.succeeded: "job.succeeded", JobStatus.failed: "job.failed"}.get(job.status)


def artifact_links(job: Job, base_url: str = "") -> list[dict[str, Any]]:
    """The job's stored results with their download links (GET /artifacts/{id}/download, prefixed by
    settings.public_base_url when set), so that a receiver needs no polling to fetch them."""
    base = base_url.rstrip("/")
    return [
        {
            "id": a.id,
            "name": a.name,
            "kind": a.kind,
            "size_bytes": a.size_bytes,
            "sha256": a.sha256,
            "download": f"{base}/artifacts/{a.id}/download",
        }
        for a in sorted(job.artifacts, key=lambda a: a.name)
    ]


def job_payload(job: Job) -> dict[str, Any]:
    return {
        "artifacts": artifact_links(job, get_settings().public_base_url),
        "job": {
            "id": job.id,
            "project_id": job.project_id,
            "status": job.status.value,
            "attempt": job.attempt,
            "error": job.error,
            "metrics": job.metrics or {},
            "outcome": (job.metrics or {}).get("outcome"),
            "timings": job.timings or {},
            "finished_at": job.finished_at.isoformat() if job.finished_at else None,
        },
    }


def enqueue(
    session: Session,
    tenant_id: str,
    event: str,
    payload: dict[str, Any],
    job_id: str | None = None,
    now: datetime | None = None,
) -> list[WebhookDelivery]:
    """A pending delivery of event to every active webhook of the tenant subscribed to it."""
    hooks = session.scalars(sa.select(Webhook).where(Webhook.tenant_id == tenant_id, Webhook.active))
    out = []
    for hook in hooks:
        if event in (hook.events or []):
            d = WebhookDelivery(
                webhook=hook, job_id=job_id, event=event, payload=payload, next_attempt_at=now or utcnow()
            )
            session.add(d)
            out.append(d)
    session.flush()
    return out


def enqueue_job_event(session: Session, job: Job, now: datetime | None = None) -> list[WebhookDelivery]:
    """Queue job.succeeded / job.failed for a job that just finished (nothing for other statuses)."""
    event = job_event(job)
    if event is None:
        return []
    return enqueue(session, job.project.tenant_id, event, job_payload(job), job_id=job.id, now=now)


def request_body(delivery: WebhookDelivery) -> bytes:
    envelope = {
        "id": delivery.id,
        "event": delivery.event,
        "created_at": delivery.created_at.isoformat() if delivery.created_at else None,
        "data": delivery.payload,
    }
    return json.dumps(envelope, separators=(",", ":"), sort_keys=True).encode()


def claim(delivery: WebhookDelivery) -> bool:
    """Record an attempt before it is made: one attempt more, and the delivery marked delivered, so that
    once committed it is never sent again, even when its outcome cannot be written (a database that is
    locked or away): at most once per event and receiver. False (and marked failed) for an inactive
    webhook, which is not sent to."""
    if not delivery.webhook.active:
        delivery.status, delivery.next_attempt_at = DeliveryStatus.failed, None
        delivery.last_error = "webhook inactive"
        return False
    delivery.attempts += 1
    delivery.status, delivery.next_attempt_at, delivery.last_error = DeliveryStatus.delivered, None, None
    return True


def send(
    session: Session,
    delivery: WebhookDelivery,
    *,
    client: httpx.Client | None = None,
    now: datetime | None = None,
    max_attempts: int = MAX_ATTEMPTS,
    base_delay_s: float = BASE_DELAY_S,
    max_delay_s: float = MAX_DELAY_S,
    timeout_s: float = TIMEOUT_S,
    allow: list | None = None,
    resolver: netguard.Resolver = netguard.system_resolver,
) -> bool:
    """Make the attempt a claim recorded (claim, committed): POST the event; on failure the delivery is
    pending again with its retry time (next_attempt_at), or failed after max_attempts; flushed, the
    caller commits. `allow`: networks a non-public receiver may be in (default:
    settings.webhook_allow_networks)."""
    now = now or utcnow()
    if allow is None:
        allow = netguard.parse_networks(get_settings().webhook_allow_networks)
    hook = delivery.webhook
    body = request_body(delivery)
    timestamp = str(int(now.timestamp()))
    headers = {
        "Content-Type": "application/json",
        "User-Agent": "midview-webhooks/1",
        EVENT_HEADER: delivery.event,
        DELIVERY_HEADER: delivery.id,
        TIMESTAMP_HEADER: timestamp,
        SIGNATURE_HEADER: sign(hook.secret, timestamp, body),
    }
    error: str | None = None
    try:
        target = netguard.resolve(hook.url, allow, resolver)
        pinned = netguard.pinned_request_args(target)
        args = dict(
            content=body,
            headers={**headers, **pinned["headers"]},
            timeout=timeout_s,
            extensions=pinned["extensions"],
            follow_redirects=False,
        )
        if client is None:
            with httpx.Client(follow_redirects=False) as own:
                r = own.post(pinned["url"], **args)
        else:
            r = client.post(pinned["url"], **args)
        if not r.is_success:
            error = f"HTTP {r.status_code}" + (" (redirects are not followed)" if r.is_redirect else "")
    except netguard.BlockedURL as e:
        error = str(e)
    except httpx.HTTPError as e:
        error = f"{type(e).__name__}: {e}"[:1000]
    if error is None:
        return True
    if delivery.attempts >= max_attempts:
        delivery.status, delivery.next_attempt_at, delivery.last_error = DeliveryStatus.failed, None, error
        log.warning("webhook delivery %s to %s failed for good: %s", delivery.id, hook.url, error)
    else:
        delivery.status, delivery.last_error = DeliveryStatus.pending, error
        delivery.next_attempt_at = now + timedelta(
            seconds=backoff_s(delivery.attempts, base_delay_s, max_delay_s)
        )
        log.info(
            "webhook delivery %s to %s failed (%s); retry at %s",
            delivery.id,
            hook.url,
            error,
            delivery.next_attempt_at.isoformat(),
        )
    session.flush()
    return False


def deliver(session: Session, delivery: WebhookDelivery, **kw: Any) -> bool:
    """Try one delivery now: the attempt recorded and committed first (claim), then sent (send), its
    failure recorded (flushed; the caller commits). kw: those of send."""
    claimed = claim(delivery)
    session.commit()
    return send(session, delivery, **kw) if claimed else False


def deliver_due(
    session: Session,
    *,
    now: datetime | None = None,
    limit: int = 100,
    client: httpx.Client | None = None,
    **kw: Any,
) -> int:
    """Try every pending delivery whose time has come (at most limit, oldest first); return how many
    succeeded. Rows are taken with SKIP LOCKED on PostgreSQL and every attempt is recorded (committed)
    before any is sent, so several beats never send one twice and an outcome that cannot be written does
    not send it again; the caller commits the failures. kw: those of send."""
    now = now or utcnow()
    stmt = (
        sa.select(WebhookDelivery)
        .where(
            WebhookDelivery.status == DeliveryStatus.pending,
            sa.or_(WebhookDelivery.next_attempt_at.is_(None), WebhookDelivery.next_attempt_at <= now),
        )
        .order_by(WebhookDelivery.next_attempt_at, WebhookDelivery.created_at)
        .limit(limit)
        .with_for_update(skip_locked=True)
    )
    due = list(session.scalars(stmt))
    if not due:
        return 0
    claimed = [d for d in due if claim(d)]
    session.commit()  # every attempt recorded before any is made (and the rows' locks released)
    own = client is None
    http = client or httpx.Client(follow_redirects=False)
    try:
        return sum(send(session, d, client=http, now=now, **kw) for d in claimed)
    finally:
        if own:
            http.close()
