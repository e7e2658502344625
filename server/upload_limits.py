"""Request body limits, enforced while the body streams in (before anything is parsed or stored).

Each route family has its own limit; a request whose Content-Length or streamed size goes
over it gets 413 with the usual JSON error body.
"""

from __future__ import annotations

import json
import re

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.asgi import BodyTooLarge, TrackingSend
from server.errors import error_body
from server.settings import Settings

_MULTIPART_OVERHEAD = 1024 * 1024  # boundaries, headers and the small form fields


def limits_for(settings: Settings) -> list[tuple[re.Pattern[str], int, str]]:
    return [
        (
            re.compile(r"^/api/v1/scenes/[^/]+/frames$"),
            6 * settings.max_frame_upload_bytes + _MULTIPART_OVERHEAD,
            "frame upload",
        ),
        (
            re.compile(r"^/api/v1/scenes/[^/]+/archive$"),
            settings.max_archive_bytes + _MULTIPART_OVERHEAD,
            "archive",
        ),
        (
            re.compile(r"^/api/v1/models$"),
            settings.max_model_upload_bytes + _MULTIPART_OVERHEAD,
            "checkpoint",
        ),
        (
            re.compile(r"^/api/v1/predict$"),
            settings.max_inference_upload_bytes + _MULTIPART_OVERHEAD,
            "image",
        ),
        # The dashboard's preview of a prediction (/ui/api/predict-preview): an image, as predict.
        (
            re.compile(r"^/api/predict-preview$"),
            settings.max_inference_upload_bytes + _MULTIPART_OVERHEAD,
            "image",
        ),
    ]


DEFAULT_LIMIT = 1024 * 1024  # JSON bodies


class BodyLimitMiddleware:
    def __init__(self, app: ASGIApp, settings: Settings):
        self.app = app
        self.rules = limits_for(settings)

    def _limit(self, path: str) -> tuple[int, str]:
        # The dashboard serves the same routes under /ui/api/v1 (server/app.py).
        path = path.removeprefix("/ui")
        for pattern, limit, what in self.rules:
            if pattern.match(path):
                return limit, what
        return DEFAULT_LIMIT, "request body"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            await self.app(scope, receive, send)
            return
        limit, what = self._limit(scope["path"])
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await self._reject(send, what, limit)
            return
        received = 0
        over = False  # the body went over the limit before the answer started

        async def limited_receive() -> Message:
            nonlocal received, over
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    over = over or not tracking_send.started
                    raise BodyTooLarge
            return message

        async def guarded_send(message: Message) -> None:
            # FastAPI turns an exception raised while it reads the body into its own 400 ("There
            # was an error parsing the body"): a body without Content-Length (chunked) that goes
            # over the limit is answered 413 all the same, instead of that answer.
            if over:
                return
            await tracking_send(message)

        tracking_send = TrackingSend(send)
        try:
            await self.app(scope, limited_receive, guarded_send)
        except Exception as exc:
            if not over and not isinstance(exc, BodyTooLarge):
                raise  # (a body over the limit after the answer started: nothing more to send)
        if over:
            await self._reject(send, what, limit)

    @staticmethod
    async def _reject(send: Send, what: str, limit: int) -> None:
        body = json.dumps(
            error_body("too_large", f"{what} exceeds the limit of {limit} bytes", what)
        ).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
