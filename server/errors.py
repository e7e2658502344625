"""API errors: every 4xx/5xx answer is ``{"error": {"code", "message", "field"}}``.

``field`` names the request field at fault (``"depth"``, ``"params.scene_id"``) or is null.
An unexpected exception is answered 500 on the same keep-alive connection (see
:class:`UnhandledErrorMiddleware`); a value the database refuses (a number out of its range,
a NUL character in text) is the client's input and is answered 422. A write that finds the
disk full is answered 507 (:func:`storage_full`; docs/operations.md "Full disk"), and one that
finds the database unreachable 503 (docs/operations.md "Database restarts").
"""

from __future__ import annotations

import errno
import logging
import os
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError, InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

from csa_core.errors import CSAInputError
from server.asgi import BodyTooLarge, TrackingSend

log = logging.getLogger(__name__)


class APIError(Exception):
    """An error the client can act on; raised anywhere in a request."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        headers: dict[str, str] | None = None,
    ):
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.headers = headers


def not_found(what: str, ident: Any) -> APIError:
    return APIError(404, "not_found", f"{what} {ident!r} not found")


def invalid(field: str, message: str) -> APIError:
    return APIError(422, "invalid", f"{field}: {message}", field=field)


def conflict(message: str, field: str | None = None) -> APIError:
    return APIError(409, "conflict", message, field=field)


def too_large(field: str, limit: int) -> APIError:
    return APIError(
        413, "too_large", f"{field}: upload exceeds the limit of {limit} bytes", field=field
    )


def not_available(message: str) -> APIError:
    return APIError(501, "not_available", message)


STORAGE_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


def storage_full(exc: BaseException) -> bool:
    """Whether ``exc`` is a write refused for want of space (a full disk or a quota)."""
    return isinstance(exc, OSError) and exc.errno in STORAGE_FULL_ERRNOS


def is_utf8_text(text: str) -> bool:
    """Whether ``text`` encodes as UTF-8: not, when it holds a lone surrogate (JSON's
    ``"\\ud800"``), which no database column holds and no answer can carry."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _printable(text: str) -> str:
    """``text`` as valid UTF-8: a name the client sent as bytes that are not UTF-8 (a tar
    member's, decoded with surrogate escapes) keeps them as ``\\udcff`` escapes, since an
    answer holding lone surrogates cannot be encoded at all."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def error_body(code: str, message: str, field: str | None = None) -> dict[str, Any]:
    return {
        "error": {
            "code": code,
            "message": _printable(message),
            "field": None if field is None else _printable(field),
        }
    }


def _field_of(loc: tuple[Any, ...] | list[Any]) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header", "form", "file"):
        parts = parts[1:]
    return ".".join(parts) or "body"


def _internal_error(exc: Exception) -> JSONResponse:
    return JSONResponse(
        error_body("internal", f"internal error: {type(exc).__name__}"), status_code=500
    )


class UnhandledErrorMiddleware:
    """Answers 500 for an exception that escapes a route, and keeps the connection open.

    Starlette's outermost error middleware also answers 500, but then re-raises, and uvicorn
    closes the connection of a request whose application raised: a client's next request on
    that keep-alive connection would fail too. This middleware sits inside the others, so the
    request metrics still count the 500. Exceptions in ``passthrough`` belong to an outer
    middleware (the upload limit answers 413) and go on; so does anything raised after the
    answer started (a broken stream cannot be answered again).
    """

    def __init__(self, app: ASGIApp, passthrough: tuple[type[BaseException], ...] = ()):
        self.app = app
        self.passthrough = passthrough

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        # A read whose pooled connection died under it (the database restarted) runs once more
        # on a fresh connection: it changes nothing, so running it twice is safe.
        tries = 2 if scope.get("method") in ("GET", "HEAD") else 1
        for attempt in range(tries):
            tracking_send = TrackingSend(send)
            try:
                await self.app(scope, receive, tracking_send)
                return
            except Exception as exc:
                if tracking_send.started or isinstance(exc, self.passthrough):
                    raise
                if isinstance(exc, PoolTimeoutError):
                    await _busy()(scope, receive, send)
                    return
                if _database_unavailable(exc):
                    if attempt + 1 < tries and getattr(exc, "connection_invalidated", False):
                        log.warning(
                            "database connection lost during %s %s; reading again",
                            scope.get("method"),
                            scope.get("path"),
                        )
                        continue
                    await _unavailable(exc)(scope, receive, send)
                    return
                log.exception("unhandled error in %s %s", scope.get("method"), scope.get("path"))
                await _internal_error(exc)(scope, receive, send)
                return


def _database_unavailable(exc: BaseException) -> bool:
    """The database cannot be reached (down, restarting, refusing connections) or stayed
    locked past the busy timeout: a state of the service, not a fault of the request."""
    return isinstance(exc, OperationalError | InterfaceError)


def _unavailable(exc: BaseException) -> JSONResponse:
    # The driver's words name the database's host and port: in the log, not in the answer.
    log.error(
        "database unavailable: %s",
        str(getattr(exc, "orig", exc)).strip()[:300] or type(exc).__name__,
    )
    return JSONResponse(
        error_body(
            "database_unavailable",
            "the service's database is unavailable (not reachable, restarting or locked); retry"
            " shortly",
        ),
        status_code=503,
        headers={"Retry-After": "5"},
    )


def _busy() -> JSONResponse:
    """Every connection of this process's database pool stayed taken for
    ``CSA_DB_POOL_TIMEOUT`` seconds: load to shed, answered before anything was written."""
    log.warning("database pool exhausted: a request waited CSA_DB_POOL_TIMEOUT for a connection")
    return JSONResponse(
        error_body(
            "database_busy",
            "every database connection of the service stayed busy; retry shortly"
            ' (docs/operations.md "Database connections")',
        ),
        status_code=503,
        headers={"Retry-After": "1"},
    )


def install_error_handlers(app: FastAPI) -> None:
    """The error answers; call before adding other middleware, so that
    :class:`UnhandledErrorMiddleware` is the innermost."""
    app.add_middleware(UnhandledErrorMiddleware, passthrough=(BodyTooLarge,))

    @app.exception_handler(APIError)
    async def _api_error(_: Request, exc: APIError) -> JSONResponse:
        return JSONResponse(
            error_body(exc.code, exc.message, exc.field),
            status_code=exc.status,
            headers=exc.headers,
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        errs = exc.errors()
        first = errs[0] if errs else {"loc": (), "msg": "invalid request"}
        field = _field_of(first.get("loc", ()))
        message = "; ".join(f"{_field_of(e.get('loc', ()))}: {e.get('msg', '')}" for e in errs[:5])
        return JSONResponse(error_body("invalid", message, field), status_code=422)

    @app.exception_handler(CSAInputError)
    async def _input(_: Request, exc: CSAInputError) -> JSONResponse:
        return JSONResponse(
            error_body("invalid", f"{exc.where}: {exc.problem}", exc.where), status_code=422
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = {
            401: "unauthorized",
            403: "forbidden",
            404: "not_found",
            405: "method_not_allowed",
            413: "too_large",
        }.get(exc.status_code, "http_error")
        return JSONResponse(
            error_body(code, str(exc.detail)),
            status_code=exc.status_code,
            headers=getattr(exc, "headers", None),
        )

    @app.exception_handler(DataError)
    async def _refused_by_database(_: Request, exc: DataError) -> JSONResponse:
        reason = str(getattr(exc, "orig", exc)).strip().splitlines()[0][:300]
        log.warning("database refused a request's value: %s", reason)
        return JSONResponse(
            error_body(
                "invalid", f"a value of this request is not accepted by the database ({reason})"
            ),
            status_code=422,
        )

    @app.exception_handler(OSError)
    async def _os_error(_: Request, exc: OSError) -> JSONResponse:
        if not storage_full(exc):
            log.exception("unhandled error", exc_info=exc)
            return _internal_error(exc)
        # The reason only, never the file name (a path of the server). Writes go to temporary
        # names first and rows commit after their files, so nothing half-written is visible.
        reason = exc.strerror or os.strerror(exc.errno or errno.ENOSPC)
        log.error("a write failed for want of space: %s", reason)
        message = (
            f"the service's data folder is full ({reason}): nothing of this request was stored;"
            " free space and retry"
        )
        return JSONResponse(error_body("insufficient_storage", message), status_code=507)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error")  # raised outside the routes (in a middleware)
        return _internal_error(exc)
