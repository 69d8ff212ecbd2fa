"""Plain ASGI middleware (safe with streamed responses such as the event stream): request logging,
and request body limits with a read timeout."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import time
import uuid
from collections.abc import Callable
from typing import Any

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


async def _reply(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] = ()) -> None:
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
