"""Dashboard sessions: an API key signs a person in once; a signed cookie carries the session.

The cookie never holds the key. It holds a random session nonce, its expiry, a key id,
``HMAC(secret, sha256(key))``, and for a key of the database its row id; every request checks
the key again, so a session ends when its key is revoked, expires or is removed from the
settings' keys, and it carries the key's scope (docs/operations.md "Dashboard").
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

from server.db.models import ApiKey
from server.errors import APIError
from server.keys import Principal, hash_secret, key_state

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
    principal: Principal | None = None  # who signed in (set by current_session)


@dataclass(frozen=True)
class SignedCookie:
    """A cookie whose signature and expiry are good: the key it names is still to be checked."""

    key_id: str
    key_row: int | None  # the database key's id; None for a settings key
    nonce: str
    expires: int


class SessionSigner:
    """Issues and checks session cookies with one secret."""

    def __init__(self, secret: bytes):
        self._secret = secret

    def _mac(self, purpose: str, value: str) -> bytes:
        return hmac.new(self._secret, f"{purpose}\0{value}".encode(), hashlib.sha256).digest()

    def key_id(self, api_key: str) -> str:
        return self.key_id_of_hash(hash_secret(api_key))

    def key_id_of_hash(self, digest: str) -> str:
        """The key id of a key's sha256: what a database key's row lets us recompute."""
        return _b64(self._mac("key", digest)[:18])

    def csrf_token(self, nonce: str) -> str:
        return _b64(self._mac("csrf", nonce))

    def issue(self, api_key: str, now: float | None = None, key_row: int | None = None) -> str:
        """The cookie value of a new session for ``api_key`` (which must be valid);
        ``key_row`` is the id of a database key."""
        now = time.time() if now is None else now
        fields: dict[str, object] = {
            "k": self.key_id(api_key),
            "n": secrets.token_urlsafe(18),
            "e": int(now) + SESSION_SECONDS,
        }
        if key_row is not None:
            fields["i"] = key_row
        payload = json.dumps(fields, separators=(",", ":"))
        body = _b64(payload.encode())
        return f"{body}.{_b64(self._mac('cookie', body))}"

    def open(self, cookie: str | None, now: float | None = None) -> SignedCookie | None:
        """The fields of a cookie this signer issued that has not expired, or None."""
        if not cookie or cookie.count(".") != 1 or len(cookie) > 512:
            return None
        body, sig = cookie.split(".")
        try:
            if not hmac.compare_digest(_unb64(sig), self._mac("cookie", body)):
                return None
            payload = json.loads(_unb64(body))
            kid, nonce, expires = str(payload["k"]), str(payload["n"]), int(payload["e"])
            row = payload.get("i")
            if row is not None and type(row) is not int:
                return None
        except (ValueError, KeyError, TypeError, AttributeError):
            return None
        if expires <= (time.time() if now is None else now):
            return None
        return SignedCookie(kid, row, nonce, expires)

    def session(self, opened: SignedCookie, principal: Principal | None = None) -> UISession:
        return UISession(opened.nonce, opened.expires, self.csrf_token(opened.nonce), principal)

    def verify(
        self, cookie: str | None, api_keys: list[str], now: float | None = None
    ) -> UISession | None:
        """The session of a cookie of one of ``api_keys`` (settings keys), or None: bad
        signature, expired, or its key is gone."""
        opened = self.open(cookie, now)
        if opened is None or opened.key_row is not None:
            return None
        if not any(hmac.compare_digest(opened.key_id, self.key_id(k)) for k in api_keys):
            return None
        return self.session(opened)


_signer_lock = threading.Lock()


def signer(request: Request) -> SessionSigner:
    """The app's signer, made on first use from the data folder's secret."""
    state = request.app.state
    if getattr(state, "ui_signer", None) is None:
        with _signer_lock:
            if getattr(state, "ui_signer", None) is None:
                state.ui_signer = SessionSigner(load_secret(state.services.settings.data_dir))
    return state.ui_signer


def valid_key(request: Request, given: str) -> Principal | None:
    """The principal of a key typed into the sign-in form, or None when it is not valid."""
    from server.auth import authenticate

    if not given:
        return None
    try:
        return authenticate(request, given)
    except APIError:
        return None


def current_session(request: Request) -> UISession | None:
    """The signed-in session with its principal, checked against the keys on every request."""
    sign = signer(request)
    opened = sign.open(request.cookies.get(COOKIE))
    if opened is None:
        return None
    services = request.app.state.services
    if opened.key_row is None:
        for digest, principal in services.key_principals.items():
            if hmac.compare_digest(opened.key_id, sign.key_id_of_hash(digest)):
                return sign.session(opened, principal)
        return None
    with services.sessions() as db:
        key = db.get(ApiKey, opened.key_row)
        if key is None or key_state(key) != "active":
            return None
        if not hmac.compare_digest(opened.key_id, sign.key_id_of_hash(key.secret_sha256)):
            return None
        return sign.session(opened, Principal(key.name, key.scope, key.id))


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
    request.state.principal = session.principal  # for the routes' scope checks and the audit log
    return session
