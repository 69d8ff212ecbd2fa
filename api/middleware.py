"""Request logging as plain ASGI middleware (safe with streamed responses such as the event stream)."""

from __future__ import annotations

import logging
import time
import uuid
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
