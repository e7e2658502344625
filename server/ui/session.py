"""Dashboard sessions: an API key signs a person in once; a signed cookie carries the session.

The cookie never holds the key. It holds a random session nonce, its expiry and a key id,
``HMAC(secret, key)``, so a session ends when its key is removed from the service's keys.
The whole value is signed with a random secret kept in ``data_dir/ui_session_secret``
(created once, mode 0600), so sessions survive restarts and are shared by every process that
uses the same data folder. The cookie is ``HttpOnly``, ``SameSite=Strict``, limited to
``/ui`` and ``Secure`` behind HTTPS.

State-changing requests also need the session's CSRF token (``HMAC(secret, nonce)``, in the
``X-CSRF-Token`` header or the ``csrf_token`` form field; pages carry it in a ``<meta>`` tag)
and an ``Origin`` (or ``Referer``) of this very service. Behind a reverse proxy that
terminates TLS, uvicorn must trust its ``X-Forwarded-Proto`` (``--forwarded-allow-ips``) so
that the service knows its own ``https://`` origin.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import os
import secrets
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from fastapi import Request

from server.errors import APIError

log = logging.getLogger(__name__)

COOKIE = "csa_session"
COOKIE_PATH = "/ui"
SESSION_SECONDS = 12 * 3600
CSRF_HEADER = "X-CSRF-Token"
CSRF_FIELD = "csrf_token"
SECRET_FILE = "ui_session_secret"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def load_secret(data_dir: Path) -> bytes:
    """The signing secret of this data folder, created on first use.

    Written to a temporary file and hard-linked into place, so two processes starting at once
    agree on one secret and neither ever reads a half-written file."""
    path = Path(data_dir) / SECRET_FILE
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{SECRET_FILE}.{os.getpid()}.{secrets.token_hex(4)}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32) + "\n")
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass  # another process made it first: use theirs
        except OSError:  # a file system without hard links
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    text = path.read_text().strip()
    if len(text) < 32:
        raise RuntimeError(f"{path}: the dashboard session secret is shorter than 32 characters")
    return text.encode()


@dataclass(frozen=True)
class UISession:
    nonce: str
    expires: int
    csrf_token: str


class SessionSigner:
    """Issues and checks session cookies with one secret."""

    def __init__(self, secret: bytes):
        self._secret = secret

    def _mac(self, purpose: str, value: str) -> bytes:
        return hmac.new(self._secret, f"{purpose}\0{value}".encode(), hashlib.sha256).digest()

    def key_id(self, api_key: str) -> str:
        return _b64(self._mac("key", api_key)[:18])

    def csrf_token(self, nonce: str) -> str:
        return _b64(self._mac("csrf", nonce))

    def issue(self, api_key: str, now: float | None = None) -> str:
        """The cookie value of a new session for ``api_key`` (which must be valid)."""
        now = time.time() if now is None else now
        payload = json.dumps(
            {
                "k": self.key_id(api_key),
                "n": secrets.token_urlsafe(18),
                "e": int(now) + SESSION_SECONDS,
            },
            separators=(",", ":"),
        )
        body = _b64(payload.encode())
        return f"{body}.{_b64(self._mac('cookie', body))}"

    def verify(
        self, cookie: str | None, api_keys: list[str], now: float | None = None
    ) -> UISession | None:
        """The session of a cookie value, or None: bad signature, expired, or its key is gone."""
        if not cookie or cookie.count(".") != 1 or len(cookie) > 512:
            return None
        body, sig = cookie.split(".")
        try:
            if not hmac.compare_digest(_unb64(sig), self._mac("cookie", body)):
                return None
            payload = json.loads(_unb64(body))
            kid, nonce, expires = str(payload["k"]), str(payload["n"]), int(payload["e"])
        except (ValueError, KeyError, TypeError):
            return None
        if expires <= (time.time() if now is None else now):
            return None
        if not any(hmac.compare_digest(kid, self.key_id(k)) for k in api_keys):
            return None
        return UISession(nonce=nonce, expires=expires, csrf_token=self.csrf_token(nonce))


_signer_lock = threading.Lock()


def signer(request: Request) -> SessionSigner:
    """The app's signer, made on first use from the data folder's secret."""
    state = request.app.state
    if getattr(state, "ui_signer", None) is None:
        with _signer_lock:
            if getattr(state, "ui_signer", None) is None:
                state.ui_signer = SessionSigner(load_secret(state.services.settings.data_dir))
    return state.ui_signer


def valid_key(request: Request, given: str) -> bool:
    keys: list[str] = request.app.state.services.api_keys
    return bool(given) and any(hmac.compare_digest(given.encode(), k.encode()) for k in keys)


def current_session(request: Request) -> UISession | None:
    return signer(request).verify(request.cookies.get(COOKIE), request.app.state.services.api_keys)


def is_https(request: Request) -> bool:
    return request.url.scheme == "https"


def same_origin(request: Request) -> bool:
    """Whether the browser says the request comes from a page of this service.

    ``Origin`` (sent by browsers with every POST) must be this service's scheme and host;
    without it, ``Referer`` must be; a request with neither is refused too."""
    own = f"{request.url.scheme}://{request.url.netloc}"
    origin = request.headers.get("origin")
    if origin is not None:
        return origin == own
    referer = request.headers.get("referer")
    if referer:
        parts = urlsplit(referer)
        return f"{parts.scheme}://{parts.netloc}" == own
    return False


def check_csrf(request: Request, session: UISession, token: str | None) -> None:
    """Refuse a state-changing request without this session's token or from another site."""
    if not same_origin(request):
        raise APIError(403, "forbidden", "cross-site request refused (Origin is not this service)")
    # Compared as bytes: compare_digest refuses str with non-ASCII characters (a TypeError).
    if not token or not hmac.compare_digest(
        token.encode("utf-8", "surrogatepass"), session.csrf_token.encode()
    ):
        raise APIError(
            403, "forbidden", f"missing or wrong CSRF token (send the {CSRF_HEADER} header)"
        )


def require_ui_session(request: Request) -> UISession:
    """Dependency of the dashboard's JSON routes: a signed-in session, and for unsafe methods
    the CSRF checks. Answers 401/403 JSON errors (the REST API's header keys are not read)."""
    session = current_session(request)
    if session is None:
        raise APIError(
            401, "unauthorized", "not signed in to the dashboard (or the session expired)"
        )
    if request.method not in SAFE_METHODS:
        check_csrf(request, session, request.headers.get(CSRF_HEADER))
    return session
