"""Small ASGI helpers shared by the service's middleware: the error middleware
(``server/errors.py``) and the body limits (``server/upload_limits.py``) both import them, and
this module imports neither."""

from __future__ import annotations

from starlette.types import Message, Send


class TrackingSend:
    """Wraps an ASGI ``send`` and records whether the response has started.

    ``started`` turns true when the ``http.response.start`` message is handed on: after that
    the status and headers are on their way and the request cannot be answered again
    (:class:`server.errors.UnhandledErrorMiddleware`,
    :class:`server.upload_limits.BodyLimitMiddleware`).
    """

    def __init__(self, send: Send):
        self._send = send
        self.started = False

    async def __call__(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            self.started = True
        await self._send(message)


class BodyTooLarge(Exception):
    """A request body went over its route's limit while it streamed in: raised by
    :class:`server.upload_limits.BodyLimitMiddleware`, which answers 413 itself, so that
    :class:`server.errors.UnhandledErrorMiddleware` lets it pass instead of answering 500."""
