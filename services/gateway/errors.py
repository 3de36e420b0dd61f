"""How failures become HTTP answers: every one a clear status and reason, never a bare 500.

Bus errors map by what they mean for the caller: nobody answered -> 503, the service said the input
was bad -> 422, over a per-request budget -> 413, not found -> 404, timeout -> 504, the service itself failed -> 502 (the gateway is fine,
what stands behind it is not).
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from shared.bus.typed import NoReplyError, RemoteError
from shared.keys import KeyExprError
from shared.schemas import ErrorCode

log = logging.getLogger(__name__)

_STATUS = {
    ErrorCode.BAD_REQUEST: 422,
    ErrorCode.NOT_FOUND: 404,
    ErrorCode.UNAVAILABLE: 503,
    ErrorCode.TIMEOUT: 504,
    ErrorCode.INTERNAL: 502,
    ErrorCode.BUDGET_EXCEEDED: 413,
}


class GatewayError(Exception):
    """Base of the gateway's own errors; ``status_code`` and ``detail`` make the HTTP answer."""

    status_code = 400

    def __init__(self, detail: str, status_code: int | None = None, code: str | None = None):
        super().__init__(detail)
        self.detail = detail
        self.code = code  # the bus error code it stands for (budget_exceeded, ...), when there is one
        if status_code is not None:
            self.status_code = status_code


def remote_status(exc: RemoteError) -> int:
    if isinstance(exc, NoReplyError):
        return 503
    return _STATUS.get(exc.code, 502)


def remote_detail(exc: RemoteError, what: str = "") -> str:
    if isinstance(exc, NoReplyError):
        return f"{what or 'the service'} is unavailable: {exc.message}"
    return f"{what + ': ' if what else ''}{exc.message}"


def ask(what: str, fn):
    """``fn()``, with a bus failure turned into the matching HTTP answer (``what`` names the request)."""
    try:
        return fn()
    except RemoteError as exc:
        raise GatewayError(remote_detail(exc, what), remote_status(exc), code=exc.code.value) from None


def install(app: FastAPI) -> None:
    async def on_remote(_request: Request, exc: RemoteError) -> JSONResponse:
        code = remote_status(exc)
        log.log(logging.WARNING if code >= 500 else logging.INFO, "bus error -> %d: %s", code, exc)
        return JSONResponse({"detail": remote_detail(exc), "code": exc.code.value}, status_code=code)

    async def on_gateway(_request: Request, exc: GatewayError) -> JSONResponse:
        body = {"detail": exc.detail} if exc.code is None else {"detail": exc.detail, "code": exc.code}
        return JSONResponse(body, status_code=exc.status_code)

    async def on_key(_request: Request, exc: KeyExprError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=422)

    async def on_invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's default echoes the offending input, and a NaN/inf in it cannot be written as JSON
        # (a 500 for bad input): answer with location, message and type only.
        detail = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
                  for e in exc.errors()]
        return JSONResponse({"detail": detail}, status_code=422)

    app.add_exception_handler(RemoteError, on_remote)
    app.add_exception_handler(RequestValidationError, on_invalid)
    app.add_exception_handler(GatewayError, on_gateway)
    app.add_exception_handler(KeyExprError, on_key)
