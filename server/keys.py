"""API keys as data, and the scopes they carry (docs/operations.md "API keys", "Scopes").

A key is ``csa_`` followed by a random secret of 32 bytes (URL-safe base64). The database keeps
only its sha256, its first characters (the prefix that lists show) and its name, scope,
expiry, creation, last use and revocation times; the key itself is shown once, when it is
made. A request's key is hashed and looked up on every request, so a revocation or an expiry
takes effect at the next request. Making, listing and revoking keys: ``server/services/keys.py``.

The keys of the settings (``CSA_API_KEYS``, or the one generated into ``data_dir/api_key``
when none is configured; ``server/auth.py``) are admin keys that live outside the database.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass
from typing import Literal, get_args

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db.models import ApiKey, utcnow
from server.errors import APIError, invalid

Scope = Literal["device", "operator", "admin"]
# Each scope allows everything the ones before it allow.
SCOPES: tuple[Scope, ...] = get_args(Scope)
DEVICE, OPERATOR, ADMIN = SCOPES

KEY_PREFIX = "csa_"
SECRET_BYTES = 32
PREFIX_CHARS = len(KEY_PREFIX) + 8  # "csa_" and 8 characters (48 bits) of the secret
NAME_PATTERN = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,63}$")
LAST_USED_RESOLUTION = dt.timedelta(seconds=60)  # last_used_at is written at most this often

_DURATION = re.compile(r"^\s*(\d{1,6})\s*([mhdw])\s*$")
_UNIT = {
    "m": dt.timedelta(minutes=1),
    "h": dt.timedelta(hours=1),
    "d": dt.timedelta(days=1),
    "w": dt.timedelta(weeks=1),
}
# The longest lifetime a key may be given. Its expiry is a datetime, which ends with the year 9999
# (999999w is past it); a key that should not expire is made without one.
MAX_DURATION = dt.timedelta(days=100 * 365)


@dataclass(frozen=True)
class Principal:
    """Who sends a request: the key's name and scope; ``key_id`` is None for settings keys."""

    name: str
    scope: Scope
    key_id: int | None = None

    def allows(self, scope: Scope) -> bool:
        return SCOPES.index(self.scope) >= SCOPES.index(scope)


def hash_secret(key: str) -> str:
    """The sha256 (hex) a key is stored and looked up by."""
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()


def new_key() -> str:
    return KEY_PREFIX + secrets.token_urlsafe(SECRET_BYTES)


def parse_duration(text: str, field: str = "expires") -> dt.timedelta:
    """``30d``, ``12h``, ``90m`` or ``2w`` as a time span of at most :data:`MAX_DURATION`; a
    422 naming ``field`` otherwise."""
    match = _DURATION.match(text or "")
    if match is None or int(match.group(1)) == 0:
        units = "a positive number and a unit m, h, d or w: 30d, 12h"
        raise invalid(field, f"{text!r} is not a duration ({units})")
    duration = int(match.group(1)) * _UNIT[match.group(2)]
    if duration > MAX_DURATION:
        raise invalid(
            field,
            f"{text!r} is more than {MAX_DURATION.days} days (leave it out for a key that does "
            "not expire)",
        )
    return duration


# The settings' generated key (CSA_API_KEYS#n cannot be a name).
GENERATED_KEY_NAME = "data-dir-api-key"


def check_name(name: str, field: str = "name") -> str:
    if not NAME_PATTERN.match(name):
        rule = "a letter, then up to 63 letters, digits, '_', '.' or '-'"
        raise invalid(field, f"{name!r} is not a key name ({rule})")
    if name == GENERATED_KEY_NAME:
        raise invalid(
            field,
            f"{name!r} names the generated settings key in the audit log; choose another name",
        )
    return name


def check_scope(scope: str, field: str = "scope") -> Scope:
    if scope not in SCOPES:
        raise invalid(field, f"{scope!r} is not a scope (one of {', '.join(SCOPES)})")
    return scope  # type: ignore[return-value]


def settings_principals(keys: list[str], generated: bool) -> dict[str, Principal]:
    """sha256 -> admin principal of each settings key, named after where it comes from."""
    if generated:
        return {hash_secret(k): Principal(GENERATED_KEY_NAME, ADMIN) for k in keys}
    return {hash_secret(k): Principal(f"CSA_API_KEYS#{i + 1}", ADMIN) for i, k in enumerate(keys)}


def key_state(key: ApiKey, now: dt.datetime | None = None) -> str:
    """``active``, ``revoked`` or ``expired``."""
    now = now or utcnow()
    if key.revoked_at is not None:
        return "revoked"
    if key.expires_at is not None and key.expires_at <= now:
        return "expired"
    return "active"


def _unauthorized(message: str) -> APIError:
    return APIError(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})


def principal_for_hash(db: Session, digest: str, settings_keys: dict[str, Principal]) -> Principal:
    """The principal of a key's sha256: a settings key, else an active key of the database;
    401 saying whether the key is unknown, revoked or expired."""
    for known, principal in settings_keys.items():
        if hmac.compare_digest(known, digest):
            return principal
    key = db.scalar(select(ApiKey).where(ApiKey.secret_sha256 == digest))
    if key is None:
        raise _unauthorized("invalid API key")
    now = utcnow()
    state = key_state(key, now)
    if state != "active":
        raise _unauthorized(f"API key {key.prefix}... ({key.name}) is {state}")
    if key.last_used_at is None or now - key.last_used_at >= LAST_USED_RESOLUTION:
        key.last_used_at = now
        db.commit()
    return Principal(key.name, check_scope(key.scope), key.id)
