"""The audit log: one row per write request of an authenticated key
(docs/operations.md "Audit log").

:class:`AuditMiddleware` sees every request; for a write (POST, PUT, PATCH, DELETE) whose key
the authentication dependency identified (``request.state.principal``: an API key or a
dashboard session), it records after the answer who (key name and scope), what (method, route
template, path, the path's ids and, for a 201, the id of what was made), when, and the status
code, refusals (403, 404, 409, 422) included. The entry is committed before the last bytes of
the answer are sent, so a client that reads the log after an answer finds it there. Requests without
a valid key are not recorded (they would let anyone fill the table; they are answered 401 and
logged). POST routes that change nothing (predictions, renders) are not writes.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.db.models import AuditEntry
from server.db.session import session_scope
from server.keys import Principal

log = logging.getLogger(__name__)

WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# POST routes that answer a computation and store nothing; under /ui/api/v1 too.
READ_ONLY_ROUTES = frozenset(
    {"/api/v1/predict", "/api/v1/scenes/{scene_ref}/render", "/ui/api/predict-preview"}
)
_CREATED_BODY_LIMIT = 64 * 1024  # a 201 answer's body is read for its "id" up to this size


def _is_read_only(template: str) -> bool:
    return template in READ_ONLY_ROUTES or (
        template.startswith("/ui/api/v1/") and template[3:] in READ_ONLY_ROUTES
    )


def _route_template(scope: Scope) -> str | None:
    """The matched route's full template (``/api/v1/scenes/{scene_ref}``): the route's own
    template (relative to the prefixes of the routers that include it) after the segments of
    the request path that those prefixes matched."""
    relative = getattr(scope.get("route"), "path", None)
    if not isinstance(relative, str):
        return None
    segments = scope["path"].rstrip("/").split("/")
    depth = relative.rstrip("/").count("/")
    return "/".join(segments[: len(segments) - depth]) + relative if depth else scope["path"]


def _created_id(body: bytes) -> Any:
    try:
        value = json.loads(body)
    except ValueError:
        return None
    return value.get("id") if isinstance(value, dict) else None


def _storable(text: str, limit: int | None = None) -> str:
    """``text`` as any database's text column holds it, cut to ``limit`` characters: a NUL
    character (a ``%00`` in the path), which PostgreSQL's text cannot hold, as the four
    characters ``\\x00``, and a lone surrogate, which cannot be encoded for the database, as
    its ``\\udcff`` escape."""
    text = text.replace("\x00", "\\x00").encode("utf-8", "backslashreplace").decode("utf-8")
    return text if limit is None else text[:limit]


def _storable_ids(ids: dict[str, Any]) -> dict[str, Any]:
    return {_storable(k): _storable(v) if isinstance(v, str) else v for k, v in ids.items()}


def record(
    sessions,
    principal: Principal,
    method: str,
    route: str,
    path: str,
    ids: dict[str, Any],
    status: int,
) -> None:
    """Commits the entry; every text is made storable first (a path may hold any character)."""
    columns = AuditEntry.__table__.columns

    def text(column: str, value: str) -> str:
        return _storable(value, columns[column].type.length)

    with session_scope(sessions) as db:
        db.add(
            AuditEntry(
                key_name=text("key_name", principal.name),
                scope=text("scope", principal.scope),
                method=text("method", method),
                route=text("route", route),
                path=text("path", path),
                ids=_storable_ids(ids),
                status=status,
            )
        )


class AuditMiddleware:
    """Records the write requests of authenticated keys (see the module's docstring)."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in WRITE_METHODS:
            await self.app(scope, receive, send)
            return
        status = 500
        json_answer = False
        body = bytearray()
        recorded = False

        async def send_wrapper(message: Message) -> None:
            nonlocal status, json_answer, recorded
            if message["type"] == "http.response.start":
                status = message["status"]
                headers = dict(message.get("headers") or [])
                json_answer = headers.get(b"content-type", b"").startswith(b"application/json")
            elif message["type"] == "http.response.body":
                if status == 201 and json_answer and len(body) <= _CREATED_BODY_LIMIT:
                    body.extend(message.get("body", b""))
                if not message.get("more_body", False) and not recorded:
                    # Before the answer's end reaches the client: whoever reads the log
                    # next sees it.
                    recorded = True
                    await self._record(
                        scope, status, bytes(body) if len(body) <= _CREATED_BODY_LIMIT else b""
                    )
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            if not recorded:  # no complete answer (an error before it, or the client left)
                await self._record(scope, status, b"")

    async def _record(self, scope: Scope, status: int, body: bytes) -> None:
        principal = (scope.get("state") or {}).get("principal")
        template = _route_template(scope)
        if not isinstance(principal, Principal) or template is None or _is_read_only(template):
            return
        ids: dict[str, Any] = {k: str(v) for k, v in (scope.get("path_params") or {}).items()}
        if status == 201 and body and (created := _created_id(body)) is not None:
            ids["created_id"] = created
        sessions = scope["app"].state.services.sessions
        try:
            await run_in_threadpool(
                record, sessions, principal, scope["method"], template, scope["path"], ids, status
            )
        except Exception:  # the answer is sent; a lost entry is logged, never a second answer
            log.exception(
                "could not record the audit entry of %s %s by %s",
                scope["method"],
                scope["path"],
                principal.name,
            )
