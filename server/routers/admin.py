"""``/api/v1/keys`` and ``/api/v1/audit``: API keys and the audit log of writes, for admin keys
(docs/operations.md). ``csa keys`` does the same from the command line (server/cli.py)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status
from sqlalchemy import Select, select

from server.auth import AdminScope
from server.db.models import ApiKey, AuditEntry
from server.deps import DbDep
from server.keys import create_key, key_state, keys_query, revoke_key
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.schemas.admin import AuditEntryOut, KeyCreate, KeyCreatedOut, KeyOut
from server.schemas.common import ERROR_RESPONSES

router = APIRouter(tags=["admin"], responses=ERROR_RESPONSES, dependencies=[AdminScope])


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


@router.post("/keys", response_model=KeyCreatedOut, status_code=status.HTTP_201_CREATED, responses={409: ERROR_RESPONSES[422]})
def make_key(body: KeyCreate, db: DbDep) -> KeyCreatedOut:
    """A new key; the answer holds the key itself, the only time it is shown (only its sha256 is stored)."""
    row, key = create_key(db, body.name, body.scope, body.expires_in)
    return KeyCreatedOut(**key_out(row).model_dump(), key=key)


@router.get("/keys", response_model=list[KeyOut], responses=PAGE_RESPONSES)
def list_keys(db: DbDep, response: Response, pages: PageDep, include_revoked: bool = True) -> list[KeyOut]:
    """The database's keys by id (the settings' keys are not listed), a page at a time."""
    return [key_out(k) for k in page(db, keys_query(include_revoked), pages, response, (ApiKey.id,))]


@router.post("/keys/{key_ref}/revoke", response_model=KeyOut, summary="revoke a key by name or prefix (effective at its next request)")
def revoke(key_ref: Annotated[str, "name or prefix"], db: DbDep) -> KeyOut:
    return key_out(revoke_key(db, key_ref))


def audit_query(key_name: str | None = None, method: str | None = None) -> Select:
    """Newest first (ids grow with time)."""
    query = select(AuditEntry).order_by(AuditEntry.id.desc())
    if key_name is not None:
        query = query.where(AuditEntry.key_name == key_name)
    if method is not None:
        query = query.where(AuditEntry.method == method.upper())
    return query


@router.get("/audit", response_model=list[AuditEntryOut], responses=PAGE_RESPONSES)
def audit_log(
    db: DbDep,
    response: Response,
    pages: PageDep,
    key_name: Annotated[str | None, Query(max_length=64, description="only this key's entries")] = None,
    method: Annotated[str | None, Query(max_length=8, description="only this method (POST, DELETE)")] = None,
) -> list[AuditEntryOut]:
    """The write requests, newest first, a page at a time: who, what, when and the status code."""
    return [AuditEntryOut.model_validate(e) for e in page(db, audit_query(key_name, method), pages, response, (AuditEntry.id,), descending=True)]
