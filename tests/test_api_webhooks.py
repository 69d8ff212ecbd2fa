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

from shared.db import crud
from shared.db.models import DeliveryStatus, JobStatus, WebhookDelivery, utcnow
from shared.webhooks import (
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    deliver_due,
    enqueue_job_event,
    verify_signature,
)


@pytest.fixture(autouse=True)
def _loopback_receivers_allowed(monkeypatch):
    """The receivers here listen on 127.0.0.1: the operator's allow-list admits it (in-process
    deliveries read it from the settings)."""
    from shared.config import get_settings

    monkeypatch.setenv("MIDVIEW_WEBHOOK_ALLOW_NETWORKS", "127.0.0.1/32")
    get_settings.cache_clear()
    yield
    get_settings.cache_clear()


class Receiver:
    """A tiny HTTP server on 127.0.0.1 recording POSTs; answers the statuses of `script` in turn
    (then 200), with `reply` as the body and, for a 3xx, a Location back to itself."""

    def __init__(self, script: list[int], reply: bytes = b"ok") -> None:
        self.script, self.requests = list(script), []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.requests.append((dict(self.headers), body))
                status = receiver.script.pop(0) if receiver.script else 200
                self.send_response(status)
                if 300 <= status < 400:
                    self.send_header("Location", receiver.url + "/moved")
                self.send_header("Content-Length", str(len(reply)))
                self.end_headers()
                self.wfile.write(reply)

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
    with api_env.session() as s:  # a stored result: the payload links to it
        key = f"tests/{ok_job}/combined/gis/cameras.geojson"
        api_env.storage.put_bytes(key, b'{"type": "FeatureCollection", "features": []}', "application/json")
        art = crud.record_artifact(s, ok_job, "gis", "combined/gis/cameras.geojson", key)
        s.commit()
        art_id = art.id
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
    (link,) = payload["data"]["artifacts"]
    assert (
        link["name"] == "combined/gis/cameras.geojson" and link["download"] == f"/artifacts/{art_id}/download"
    )
    got = c.get(link["download"], headers=t.headers)
    assert got.status_code == 200 and got.json()["type"] == "FeatureCollection"
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


# -- server-side request forgery ---------------------------------------------------------------------
INTERNAL_URLS = (
    "http://127.0.0.1:6379/",
    "http://localhost:6379/",
    "http://LOCALHOST./x",
    "http://api.localhost/x",
    "http://0x7f000001/",
    "http://2130706433/",
    "http://0177.0.0.1/",
    "http://127.1/",
    "http://0.0.0.0/",
    "http://[::1]/",
    "http://[::ffff:127.0.0.1]/",
    "http://[::ffff:7f00:1]/",
    "http://[64:ff9b::a9fe:a9fe]/",  # NAT64 of 169.254.169.254
    "http://[2002:a00:1::]/",  # 6to4 of 10.0.0.1
    "http://169.254.169.254/latest/meta-data/",
    "http://10.0.0.1/",
    "http://172.16.5.4/",
    "http://192.168.1.1/",
    "http://100.64.0.1/",
    "http://224.0.0.1/",
    "http://240.0.0.1/",
    "http://[fd00::1]/",
    "http://[fe80::1]/",
    "http://[ff02::1]/",
)


def test_webhook_urls_naming_internal_addresses_are_refused(tmp_path, request) -> None:
    """POST /webhooks refuses every encoding of a non-public address with 422 and the reason (an
    operator's allow-list is not set here); nothing is stored and nothing is sent."""
    from conftest import ApiEnv, make_api_settings
    from fastapi.testclient import TestClient

    from api.main import create_app
    from shared.db.models import Webhook

    settings = make_api_settings("sqlite-local", tmp_path, request, webhook_allow_networks="")
    with TestClient(create_app(settings)) as c:
        env = ApiEnv("sqlite-local", c.app, c, None)
        headers = env.tenant().headers
        for url in INTERNAL_URLS:
            r = c.post("/webhooks", json={"url": url}, headers=headers)
            assert r.status_code == 422, (url, r.text)
            assert "refused" in r.text or "local name" in r.text, (url, r.text)
        assert (
            c.post("/webhooks", json={"url": "https://hooks.example.com/x"}, headers=headers).status_code
            == 201
        )
        with env.session() as s:
            assert [h.url for h in s.scalars(sa.select(Webhook))] == ["https://hooks.example.com/x"]


def test_netguard_resolves_at_delivery_time_and_checks_every_address() -> None:
    from shared import netguard

    names = {
        "hooks.example.com": ["93.184.216.34"],
        "internal.example.com": ["10.1.2.3"],
        "rebind.example.com": ["93.184.216.34", "127.0.0.1"],
        "v6.example.com": ["::1"],
        "mapped.example.com": ["::ffff:169.254.169.254"],
    }
    resolver = lambda host, port: names[host]  # noqa: E731  (no DNS: the test sends nothing)
    t = netguard.resolve("https://hooks.example.com:8443/a?b=1", [], resolver)
    assert t.address == "93.184.216.34" and t.pinned_url == "https://93.184.216.34:8443/a?b=1"
    args = netguard.pinned_request_args(t)
    assert args["headers"] == {"Host": "hooks.example.com:8443"}
    assert args["extensions"] == {"sni_hostname": "hooks.example.com"}
    for host, why in (
        ("internal.example.com", "private"),
        ("rebind.example.com", "loopback"),
        ("v6.example.com", "loopback"),
        ("mapped.example.com", "private|link-local"),
    ):
        with pytest.raises(netguard.BlockedURL, match=why):
            netguard.resolve(f"http://{host}/", [], resolver)
    allow = netguard.parse_networks("10.1.0.0/16")
    assert netguard.resolve("http://internal.example.com/", allow, resolver).address == "10.1.2.3"
    for bad in ("ftp://hooks.example.com/", "http://user:pw@hooks.example.com/", "http:///x"):
        with pytest.raises(netguard.BlockedURL):
            netguard.resolve(bad, [], resolver)
    with pytest.raises(ValueError, match="CIDR"):
        netguard.parse_networks("10.0.0.0/33")


def test_delivery_to_a_name_resolving_to_loopback_is_refused_before_connecting(api_env) -> None:
    """A webhook on a host name passes registration; at delivery its address is loopback: refused, the
    receiver gets nothing. With the operator's allow-list the same delivery goes to the checked address
    (Host header kept); a redirect is not followed and the receiver's body is never recorded."""
    from shared import netguard
    from shared.webhooks import deliver

    receiver = Receiver([302, 500], reply=b"internal secret: db password hunter2")
    try:
        port = receiver.server.server_address[1]
        resolver = lambda host, p: ["127.0.0.1"] if host == "receiver.example.com" else []  # noqa: E731
        c, t = api_env.client, api_env.tenant()
        hook = c.post(
            "/webhooks", json={"url": f"http://receiver.example.com:{port}/hook"}, headers=t.headers
        ).json()
        job_id = _finished_job(api_env, t, JobStatus.succeeded)
        now = utcnow()
        with api_env.session() as s:
            (d,) = enqueue_job_event(s, crud.get_job(s, job_id), now=now)
            assert not deliver(s, d, now=now, allow=[], resolver=resolver)
            assert "refused: loopback address 127.0.0.1" in d.last_error
            s.commit()
        assert receiver.requests == []
        allow = netguard.parse_networks("127.0.0.1/32")
        with api_env.session() as s:
            d = s.get(WebhookDelivery, d.id)
            assert not deliver(s, d, now=now, allow=allow, resolver=resolver)  # 302: not followed
            assert d.last_error == "HTTP 302 (redirects are not followed)"
            assert not deliver(s, d, now=now, allow=allow, resolver=resolver)  # 500 with a body
            assert d.last_error == "HTTP 500"
            assert deliver(s, d, now=now, allow=allow, resolver=resolver)
            s.commit()
        assert len(receiver.requests) == 3  # the redirect's target was never asked
        assert all(h["Host"] == f"receiver.example.com:{port}" for h, _ in receiver.requests)
        rows = c.get(f"/webhooks/{hook['id']}/deliveries", headers=t.headers).text
        assert "hunter2" not in rows
    finally:
        receiver.close()


def test_a_host_name_resolving_to_an_internal_address_is_refused_at_registration(
    tmp_path, request, monkeypatch
) -> None:
    """POST /webhooks resolves a host name too: one that points at loopback or a private network now is
    422 (not only refused at delivery); one that does not resolve yet is left to the delivery's check."""
    from conftest import ApiEnv, make_api_settings
    from fastapi.testclient import TestClient

    from api.main import create_app
    from shared import netguard

    names = {"evil.example.com": ["127.0.0.1"], "lan.example.com": ["93.184.216.34", "192.168.1.5"]}

    def resolver(host: str, port: int) -> list[str]:
        if host not in names:
            raise netguard.BlockedURL(f"cannot resolve {host}")
        return names[host]

    monkeypatch.setattr(netguard, "system_resolver", resolver)
    settings = make_api_settings("sqlite-local", tmp_path, request, webhook_allow_networks="")
    with TestClient(create_app(settings)) as c:
        headers = ApiEnv("sqlite-local", c.app, c, None).tenant().headers
        for url, why in (("http://evil.example.com/h", "loopback"), ("https://lan.example.com/h", "private")):
            r = c.post("/webhooks", json={"url": url}, headers=headers)
            assert r.status_code == 422 and why in r.text, (url, r.text)
        r = c.post("/webhooks", json={"url": "https://not-yet.example.com/h"}, headers=headers)
        assert r.status_code == 201


def test_a_delivery_whose_outcome_cannot_be_written_is_not_sent_again(api_env) -> None:
    """The receiver gets the event; writing the outcome then fails (the transaction is lost, as when an
    embedded database stays locked): the next beats send nothing more. Every attempt is recorded before
    it is made: at most one POST per event and receiver."""
    receiver = Receiver([])
    try:
        c, t = api_env.client, api_env.tenant()
        c.post("/webhooks", json={"url": receiver.url, "events": ["job.succeeded"]}, headers=t.headers)
        job_id = _finished_job(api_env, t, JobStatus.succeeded)
        t0 = utcnow()
        with api_env.session() as s:
            assert len(enqueue_job_event(s, crud.get_job(s, job_id), now=t0)) == 1
            s.commit()
        with api_env.session() as s:
            assert deliver_due(s, now=t0) == 1
            s.rollback()  # the outcome's transaction is lost
        for later in (60, 3600):
            with api_env.session() as s:
                assert deliver_due(s, now=t0 + timedelta(seconds=later)) == 0
                s.commit()
        assert len(receiver.requests) == 1
    finally:
        receiver.close()
