"""Webhooks: the API to manage them, and signed deliveries with retries against a local HTTP server."""

from __future__ import annotations

import hashlib
import hmac
import json
import threading
from collections.abc import Iterator
from datetime import timedelta
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
import sqlalchemy as sa

from api.webhooks import (
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    deliver_due,
    enqueue_job_event,
    verify_signature,
)
from shared.db import crud
from shared.db.models import DeliveryStatus, JobStatus, WebhookDelivery, utcnow


class Receiver:
    """A tiny HTTP server on 127.0.0.1 recording POSTs; answers the statuses of `script` in turn
    (then 200)."""

    def __init__(self, script: list[int]) -> None:
        self.script, self.requests = list(script), []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.requests.append((dict(self.headers), body))
                status = receiver.script.pop(0) if receiver.script else 200
                self.send_response(status)
                self.send_header("Content-Length", "2")
                self.end_headers()
                self.wfile.write(b"ok")

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    r = Receiver([500])
    yield r
    r.close()


def test_webhook_api(api_env) -> None:
    c, t, other = api_env.client, api_env.tenant(), api_env.tenant()
    r = c.post("/webhooks", json={"url": "https://example.com/hook"}, headers=t.headers)
    assert r.status_code == 201
    hook = r.json()
    assert hook["secret"].startswith("whsec_") and hook["events"] == ["job.failed", "job.succeeded"]
    listed = c.get("/webhooks", headers=t.headers).json()
    assert [h["id"] for h in listed] == [hook["id"]] and "secret" not in listed[0]  # shown once only
    assert "secret" not in c.get(f"/webhooks/{hook['id']}", headers=t.headers).json()
    for bad in (
        {"url": "ftp://example.com"},
        {"url": "not a url"},
        {"url": "http://x", "events": ["job.odd"]},
        {"url": "http://x", "events": []},
    ):
        assert c.post("/webhooks", json=bad, headers=t.headers).status_code == 422, bad
    assert c.get(f"/webhooks/{hook['id']}", headers=other.headers).status_code == 404
    assert c.get("/webhooks", headers=other.headers).json() == []
    assert c.delete(f"/webhooks/{hook['id']}", headers=other.headers).status_code == 404
    assert c.delete(f"/webhooks/{hook['id']}", headers=t.headers).status_code == 204
    assert c.get("/webhooks", headers=t.headers).json() == []


def _finished_job(env, tenant, status: JobStatus) -> str:
    with env.session() as s:
        project = crud.create_project(s, tenant.id, f"p-{status.value}")
        job = crud.create_job(s, project.id)
        crud.set_job_status(s, job, JobStatus.running)
        crud.set_job_status(s, job, status, error="boom" if status == JobStatus.failed else None)
        s.commit()
        return job.id


def test_delivery_is_signed_and_retried(api_env, receiver: Receiver) -> None:
    c, t = api_env.client, api_env.tenant()
    hook = c.post(
        "/webhooks", json={"url": receiver.url, "events": ["job.succeeded"]}, headers=t.headers
    ).json()
    ok_job = _finished_job(api_env, t, JobStatus.succeeded)
    failed_job = _finished_job(api_env, t, JobStatus.failed)  # not subscribed: no delivery
    t0 = utcnow()
    with api_env.session() as s:
        assert len(enqueue_job_event(s, crud.get_job(s, ok_job), now=t0)) == 1
        assert enqueue_job_event(s, crud.get_job(s, failed_job), now=t0) == []
        s.commit()

    with api_env.session() as s:  # first try: the receiver answers 500
        assert deliver_due(s, now=t0) == 0
        s.commit()
        d = s.scalar(sa.select(WebhookDelivery).where(WebhookDelivery.webhook_id == hook["id"]))
        assert d.status == DeliveryStatus.pending and d.attempts == 1 and "HTTP 500" in d.last_error
        assert d.next_attempt_at == t0 + timedelta(seconds=30)
    with api_env.session() as s:  # not due yet
        assert deliver_due(s, now=t0 + timedelta(seconds=10)) == 0
        s.commit()
    assert len(receiver.requests) == 1
    with api_env.session() as s:  # the retry succeeds
        assert deliver_due(s, now=t0 + timedelta(seconds=31)) == 1
        s.commit()
    with api_env.session() as s:
        assert deliver_due(s, now=t0 + timedelta(hours=1)) == 0  # nothing left
    assert len(receiver.requests) == 2

    headers, body = receiver.requests[-1]
    payload = json.loads(body)
    assert payload["event"] == "job.succeeded" and payload["data"]["job"]["id"] == ok_job
    assert payload["data"]["job"]["status"] == "succeeded"
    assert payload["id"] == json.loads(receiver.requests[0][1])["id"]  # one delivery id across retries
    timestamp, signature = headers[TIMESTAMP_HEADER], headers[SIGNATURE_HEADER]
    expected = hmac.new(hook["secret"].encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
    assert signature == f"sha256={expected}"
    sent_at = t0 + timedelta(seconds=31)
    assert verify_signature(hook["secret"], body, timestamp, signature, now=sent_at)
    assert not verify_signature("whsec_other", body, timestamp, signature, now=sent_at)
    assert not verify_signature(hook["secret"], body + b" ", timestamp, signature, now=sent_at)
    assert not verify_signature(hook["secret"], body, timestamp, signature, now=sent_at + timedelta(hours=1))

    rows = c.get(f"/webhooks/{hook['id']}/deliveries", headers=t.headers).json()
    assert [(d["status"], d["attempts"], d["last_error"]) for d in rows] == [("delivered", 2, None)]


def test_delivery_gives_up_after_max_attempts(api_env) -> None:
    receiver = Receiver([503] * 10)
    try:
        t = api_env.tenant()
        api_env.client.post("/webhooks", json={"url": receiver.url}, headers=t.headers)
        job_id = _finished_job(api_env, t, JobStatus.failed)
        now = utcnow()
        with api_env.session() as s:
            enqueue_job_event(s, crud.get_job(s, job_id), now=now)
            s.commit()
        for i in range(3):
            with api_env.session() as s:
                deliver_due(s, now=now + timedelta(hours=i), max_attempts=3)
                s.commit()
        with api_env.session() as s:
            d = s.scalar(sa.select(WebhookDelivery).where(WebhookDelivery.job_id == job_id))
            assert d.status == DeliveryStatus.failed and d.attempts == 3 and d.next_attempt_at is None
            assert json.loads(receiver.requests[0][1])["event"] == "job.failed"
        assert len(receiver.requests) == 3
    finally:
        receiver.close()
