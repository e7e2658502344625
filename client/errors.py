"""Typed errors of the CSA client; every message is one readable line."""

from __future__ import annotations


class CSAError(Exception):
    """Base class of everything the client raises."""


class CSAConnectionError(CSAError):
    """The server could not be reached."""


class CSATimeout(CSAError):
    """The server did not answer in time."""


class CSAHTTPError(CSAError):
    """The server answered with an error status; ``code`` and ``field`` come from its JSON body."""

    def __init__(
        self,
        status: int,
        message: str,
        code: str = "http_error",
        field: str | None = None,
        method: str = "",
        url: str = "",
    ):
        self.status = status
        self.code = code
        self.field = field
        self.method = method
        self.url = url
        super().__init__(message)

    def __str__(self) -> str:
        where = f" ({self.method} {self.url})" if self.method else ""
        return f"HTTP {self.status} {self.code}: {self.args[0]}{where}"


class AuthError(CSAHTTPError):
    """401: missing or wrong API key."""


class NotFound(CSAHTTPError):
    """404: no such scene, frame, job or model."""


class Conflict(CSAHTTPError):
    """409: the request clashes with what is stored (e.g. a frame name with other content)."""


class TooLarge(CSAHTTPError):
    """413: the upload is over the server's limit."""


class InvalidInput(CSAHTTPError):
    """422: the request is invalid; ``field`` names the culprit."""


class NotAvailable(CSAHTTPError):
    """501: this server build lacks the capability (e.g. ``adapt`` before it is installed)."""


class ServerError(CSAHTTPError):
    """5xx: the server failed."""


class JobFailed(CSAError):
    """A job the client waited for ended failed or cancelled."""

    def __init__(self, job):
        self.job = job
        super().__init__(f"job {job.id} ({job.kind}) {job.status}: {job.error or job.message}")


_BY_STATUS: dict[int, type[CSAHTTPError]] = {
    401: AuthError,
    403: AuthError,
    404: NotFound,
    409: Conflict,
    413: TooLarge,
    422: InvalidInput,
    501: NotAvailable,
}


def error_for_status(status: int) -> type[CSAHTTPError]:
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    return ServerError if status >= 500 else CSAHTTPError
