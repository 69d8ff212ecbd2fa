"""Errors as JSON `{"detail": ...}`: crud, POS and storage exceptions mapped to HTTP statuses."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from services.pos import PosError
from shared.db.crud import ConflictError, InvalidTransitionError, NotFoundError
from shared.storage import InvalidKeyError, StorageError, StorageKeyError

log = logging.getLogger("midview.api")


def error(status_code: int, detail: object, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status_code, headers=headers)


def pos_error_detail(e: PosError, message: str = "invalid POS") -> dict[str, object]:
    """The 422 body of a POS error: a message and one entry per bad row."""
    return {"message": message, "errors": e.errors}


def _printable(value: object) -> object:
    """A validation error's field as the UTF-8 response can carry it: lone surrogates (valid in JSON
    escapes, not in UTF-8) replaced, in strings and in the parts of a location."""
    if isinstance(value, str):
        return value.encode("utf-8", "replace").decode("utf-8")
    if isinstance(value, list | tuple):
        return [_printable(v) for v in value]
    return value


def validation_detail(errors: Sequence[Any], request: Request) -> list[dict]:
    """A 422's errors: the first few (settings.max_validation_errors), each with its location, message
    and type, and the offending input only when it is short: a large body is never echoed back."""
    limit = getattr(getattr(request.app.state, "settings", None), "max_validation_errors", 20)
    out = []
    for err in errors[:limit]:
        item = {k: _printable(err[k]) for k in ("type", "loc", "msg") if k in err}
        try:  # the response is UTF-8: a lone surrogate in the input cannot be echoed
            text = json.dumps(err["input"], allow_nan=False, ensure_ascii=False) if "input" in err else None
            if text is not None:
                text.encode("utf-8")
        except (TypeError, ValueError):  # NaN, bytes, lone surrogates ...: not shown
            text = None
        if text is not None and len(text) <= 200:
            item["input"] = err["input"]
        out.append(item)
    if len(errors) > limit:
        out.append({"type": "too_many_errors", "loc": [], "msg": f"{len(errors) - limit} more errors"})
    return out


def install_error_handlers(app: FastAPI) -> None:
    """Map library exceptions that escape a route to statuses (HTTPException keeps its own)."""

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, e: RequestValidationError) -> JSONResponse:
        return error(status.HTTP_422_UNPROCESSABLE_CONTENT, validation_detail(e.errors(), request))

    @app.exception_handler(NotFoundError)
    async def _not_found(_: Request, e: NotFoundError) -> JSONResponse:
        return error(status.HTTP_404_NOT_FOUND, str(e))

    @app.exception_handler(ConflictError)
    async def _conflict(_: Request, e: ConflictError) -> JSONResponse:
        return error(status.HTTP_409_CONFLICT, str(e))

    @app.exception_handler(InvalidTransitionError)
    async def _transition(_: Request, e: InvalidTransitionError) -> JSONResponse:
        return error(status.HTTP_409_CONFLICT, str(e))

    @app.exception_handler(PosError)
    async def _pos(_: Request, e: PosError) -> JSONResponse:
        return error(status.HTTP_422_UNPROCESSABLE_CONTENT, pos_error_detail(e))

    @app.exception_handler(InvalidKeyError)
    async def _key(_: Request, e: InvalidKeyError) -> JSONResponse:
        return error(status.HTTP_422_UNPROCESSABLE_CONTENT, str(e))

    @app.exception_handler(StorageKeyError)
    async def _missing_object(_: Request, e: StorageKeyError) -> JSONResponse:
        return error(status.HTTP_404_NOT_FOUND, f"stored object missing: {e}")

    @app.exception_handler(StorageError)
    async def _storage(request: Request, e: StorageError) -> JSONResponse:
        log.error("storage error on %s %s: %s", request.method, request.url.path, e)
        return error(status.HTTP_502_BAD_GATEWAY, f"storage error: {e}")

    @app.exception_handler(Exception)
    async def _internal(request: Request, e: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error(status.HTTP_500_INTERNAL_SERVER_ERROR, "internal server error")
