"""API keys in the database: make, list and revoke them (``/api/v1/keys``, ``csa keys``).

What a key is (its form, scopes, names, lifetimes) and how a request's key is checked are
``server/keys.py``'s; the settings' keys live outside the database and are not listed here.
"""

from __future__ import annotations

from collections.abc import Mapping

from sqlalchemy import Select, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.db.models import ApiKey, utcnow
from server.errors import APIError, conflict, not_found
from server.keys import (
    KEY_PREFIX,
    PREFIX_CHARS,
    check_name,
    check_scope,
    hash_secret,
    key_state,
    new_key,
    parse_duration,
)
from server.schemas.admin import KeyOut

ORDER = (ApiKey.id,)  # the sort key of :func:`keys_query` (server/pagination.py)


def key_out(key: ApiKey) -> KeyOut:
    return KeyOut(
        id=key.id,
        name=key.name,
        prefix=key.prefix,
        scope=key.scope,
        state=key_state(key),
        created_at=key.created_at,
        expires_at=key.expires_at,
        last_used_at=key.last_used_at,
        revoked_at=key.revoked_at,
    )


def _name_taken(name: str) -> APIError:
    message = f"a key named {name!r} exists (names stay taken after revocation)"
    return conflict(message, field="name")


# The names errors give the parameters of :func:`create_key`: the request body's fields.
KEY_FIELDS = {"name": "name", "scope": "scope", "expires_in": "expires_in"}


def create_key(
    db: Session,
    name: str,
    scope: str,
    expires_in: str | None = None,
    fields: Mapping[str, str] = KEY_FIELDS,
) -> tuple[ApiKey, str]:
    """A new key row and the key itself (shown once: only its hash is stored). An invalid
    parameter is a 422 naming it as ``fields`` does (``csa keys create`` names its options)."""
    check_name(name, fields["name"])
    scope = check_scope(scope, fields["scope"])
    expires = parse_duration(expires_in, fields["expires_in"]) if expires_in else None
    expires_at = utcnow() + expires if expires is not None else None
    if db.scalar(select(ApiKey.id).where(ApiKey.name == name)) is not None:
        raise _name_taken(name)
    for _ in range(3):  # a prefix collision (48 random bits) is retried with a new secret
        key = new_key()
        row = ApiKey(
            name=name,
            prefix=key[:PREFIX_CHARS],
            secret_sha256=hash_secret(key),
            scope=scope,
            expires_at=expires_at,
        )
        db.add(row)
        try:
            db.commit()
            return row, key
        except IntegrityError:
            db.rollback()
            if db.scalar(select(ApiKey.id).where(ApiKey.name == name)) is not None:
                raise _name_taken(name) from None
    raise APIError(500, "internal", "could not make a key with a unique prefix; try again")


def find_key(db: Session, ref: str) -> ApiKey:
    """A key by its name or by its prefix (as lists show it, with or without ``csa_``)."""
    prefixes = {ref, KEY_PREFIX + ref} if not ref.startswith(KEY_PREFIX) else {ref}
    named = or_(ApiKey.name == ref, ApiKey.prefix.in_(prefixes))
    key = db.scalar(select(ApiKey).where(named).limit(1))
    if key is None:
        raise not_found("API key", ref)
    return key


def revoke_key(db: Session, ref: str) -> ApiKey:
    """Revoke a key (kept for the audit log); revoking a revoked key changes nothing."""
    key = find_key(db, ref)
    if key.revoked_at is None:
        key.revoked_at = utcnow()
        db.commit()
    return key


def keys_query(include_revoked: bool = True) -> Select:
    """The database's keys by id (:data:`ORDER`), revoked ones too unless told otherwise."""
    query = select(ApiKey).order_by(*ORDER)
    return query if include_revoked else query.where(ApiKey.revoked_at.is_(None))
