"""Plain ASGI middleware (safe with streamed responses such as the event stream): request logging,
request body limits with a read timeout, credentials refused in query strings (and redacted from the
server's access log), and the dashboard's security headers."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import json
import logging
import re
import time
import uuid
from collections.abc import Callable, Sequence
from typing import Any
from urllib.parse import parse_qsl

from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("midview.api.access")


class RequestLogMiddleware:
    """Logs `METHOD path status duration tenant` per request and sets an `X-Request-ID` response header
    (the client's own, when it sent one)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        request_id = headers.get(b"x-request-id", b"").decode("latin-1")[:64] or uuid.uuid4().hex
        t0 = time.perf_counter()
        status: dict[str, Any] = {"code": 500}

        async def send_logged(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"], (b"x-request-id", request_id.encode("latin-1"))]
            await send(message)

        try:
            await self.app(scope, receive, send_logged)
        finally:
            state = scope.get("state") or {}
            log.info(
                "%s %s %s %.1fms tenant=%s request=%s",
                scope["method"],
                scope["path"],
                status["code"],
                (time.perf_counter() - t0) * 1000,
                state.get("tenant_id", "-"),
                request_id,
            )


class BodyTooLarge(Exception):
    pass


async def _reply(send: Send, status: int, detail: str, headers: Sequence[tuple[bytes, bytes]] = ()) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class BodyLimitMiddleware:
    """413 for a request body over its route's limit: at once when Content-Length says so (nothing is
    read), else as soon as the streamed bytes pass it; 408 when the client stops sending its body for
    `read_timeout_s`. `limit_for(method, path)` gives the limit in bytes (None: no body expected)."""

    def __init__(self, app: ASGIApp, limit_for: Callable[[str, str], int], read_timeout_s: float) -> None:
        self.app, self.limit_for, self.read_timeout_s = app, limit_for, read_timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope["method"], scope["path"])
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None:
            try:
                size = int(declared)
            except ValueError:
                await _reply(send, 400, "Content-Length is not a number")
                return
            if size > limit:
                await _reply(send, 413, f"request body of {size} bytes is over this route's limit of {limit}")
                return
        received = 0
        state: dict[str, Any] = {"started": False, "error": None, "body_done": False}

        async def limited_receive() -> Message:
            nonlocal received
            if state["body_done"]:  # the body is in; what comes now is the disconnect, whenever it comes
                return await receive()  # (a streaming response, an event stream, waits for it)
            try:
                message = await asyncio.wait_for(receive(), self.read_timeout_s)
            except TimeoutError:
                state["error"] = (408, f"no request body data for {self.read_timeout_s:g} s")
                raise _ReadTimeout from None
            if message["type"] == "http.request":
                state["body_done"] = not message.get("more_body", False)
                received += len(message.get("body", b""))
                if received > limit:
                    state["error"] = (413, f"request body is over this route's limit of {limit} bytes")
                    raise BodyTooLarge
            return message

        async def guarded_send(message: Message) -> None:
            if state["error"] is not None and not state["started"]:
                return  # the route's own answer to a body cut short (FastAPI makes it a 400): ours instead
            if message["type"] == "http.response.start":
                state["started"] = True
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except (BodyTooLarge, _ReadTimeout):
            pass
        except Exception:
            if state["error"] is None:
                raise
        if state["error"] is not None and not state["started"]:
            await _reply(send, *state["error"])


class _ReadTimeout(Exception):
    pass


def route_limits(rules: list[tuple[str, str, int]], default: int) -> Callable[[str, str], int]:
    """limit_for(method, path) from (method, path regex, bytes) rules, first match, else `default`."""
    compiled = [(m, re.compile(p), n) for m, p, n in rules]

    def limit_for(method: str, path: str) -> int:
        for m, rx, n in compiled:
            if m == method and rx.fullmatch(path):
                return n
        return default

    return limit_for


# query parameters that carry credentials: an access log (uvicorn's, a proxy's) writes query strings out
# (not `key`: a job's idempotency key is a query parameter of GET .../jobs)
CREDENTIAL_PARAMS = {"api_key", "apikey", "api-key", "access_token", "x-api-key", "authorization"}
# an API key as any parameter's value: its prefix (shared.db.crud.API_KEY_PREFIX) and a key's length
CREDENTIAL_VALUE = re.compile(r"^mv_[A-Za-z0-9_-]{20,}$")


def credential_params(query: str) -> list[str]:
    """Names of the query parameters that carry a credential (by name, or an API key as value)."""
    pairs = parse_qsl(query, keep_blank_values=True)
    return sorted({k for k, v in pairs if k.lower() in CREDENTIAL_PARAMS or CREDENTIAL_VALUE.match(v)})


def redact_query(path: str) -> str:
    """A request path with the values of credential-carrying query parameters replaced by ***."""
    base, sep, query = path.partition("?")
    if not sep:
        return path
    bad = set(credential_params(query))
    parts = []
    for item in query.split("&"):
        name, eq, _ = item.partition("=")
        value = item.partition("=")[2]
        hidden = name.lower() in CREDENTIAL_PARAMS or name in bad or CREDENTIAL_VALUE.match(value)
        parts.append(f"{name}{eq}***" if eq and hidden else item)
    return f"{base}?{'&'.join(parts)}"


class RedactCredentials(logging.Filter):
    """For uvicorn's access log (its record args: client, method, path, version, status): credential
    values in the path's query string are written as ***."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) >= 3 and isinstance(args[2], str) and "?" in args[2]:
            record.args = (*args[:2], redact_query(args[2]), *args[3:])
        return True


class QueryCredentialsMiddleware:
    """Refuses (400, with the reason) a request whose query string carries a credential: API keys go in
    the Authorization header, never in a URL that logs, histories and proxies keep."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        query = scope.get("query_string", b"").decode("latin-1") if scope["type"] == "http" else ""
        bad = credential_params(query) if query else []
        if not bad:
            await self.app(scope, receive, send)
            return
        body = json.dumps(
            {"detail": f"credentials in the query string are refused ({', '.join(bad)}): send the API key in"
             " the Authorization header (Bearer)"}
        ).encode()  # fmt: skip
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await send({"type": "http.response.start", "status": 400, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def inline_script_hashes(html: str) -> list[str]:
    """CSP sources ('sha256-...') of a page's inline <script> blocks (the dashboard's import map)."""
    blocks = re.findall(r"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", html, re.DOTALL)
    return [f"'sha256-{base64.b64encode(hashlib.sha256(b.encode()).digest()).decode()}'" for b in blocks]


def dashboard_headers(script_hashes: list[str]) -> list[tuple[bytes, bytes]]:
    """The dashboard's security headers: a Content-Security-Policy that allows its own files (scripts
    from /ui/ and its inline import map by hash, styles, images from data: and blob: URLs, the API),
    no framing, no MIME sniffing."""
    csp = (
        "default-src 'self'; script-src 'self' "
        + " ".join(script_hashes)
        + "; style-src 'self' 'unsafe-inline';"
        " img-src 'self' data: blob:; connect-src 'self'; object-src 'none'; base-uri 'self';"
        " frame-ancestors 'none'; form-action 'self'"
    )
    return [
        (b"content-security-policy", csp.encode()),
        (b"x-content-type-options", b"nosniff"),
        (b"x-frame-options", b"DENY"),
        (b"referrer-policy", b"no-referrer"),
    ]


class SecurityHeadersMiddleware:
    """Adds `headers` to every response under `prefix` (the dashboard's /ui/)."""

    def __init__(self, app: ASGIApp, prefix: str, headers: list[tuple[bytes, bytes]]) -> None:
        self.app, self.prefix, self.headers = app, prefix, headers

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope["path"].startswith(self.prefix):
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), *self.headers]
            await send(message)

        await self.app(scope, receive, send_with_headers)


class KeyConcurrencyLimit:
    """At most `limit` requests of one API key (its Authorization header) in flight in this process: one
    more is answered 429 at once, before it takes a database connection or a worker thread, so that a
    burst from one key cannot hold the pools other tenants need. Requests without the header pass (the
    API refuses them at once)."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app, self.limit = app, int(limit)
        self._in_flight: dict[bytes, int] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        header = dict(scope.get("headers") or []).get(b"authorization") if scope["type"] == "http" else None
        if not header:
            await self.app(scope, receive, send)
            return
        who = hashlib.sha256(header).digest()  # not the key itself
        if self._in_flight.get(who, 0) >= self.limit:
            body = json.dumps(
                {"detail": f"more than {self.limit} requests of this API key at once; retry in 1 s"}
            ).encode()
            headers = [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"retry-after", b"1"),
            ]
            await send({"type": "http.response.start", "status": 429, "headers": headers})
            await send({"type": "http.response.body", "body": body})
            return
        self._in_flight[who] = self._in_flight.get(who, 0) + 1
        try:
            await self.app(scope, receive, send)
        finally:
            n = self._in_flight.pop(who) - 1
            if n:
                self._in_flight[who] = n
