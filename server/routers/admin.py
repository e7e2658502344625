"""``/api/v1/keys`` and ``/api/v1/audit``: API keys and the audit log of writes, for admin keys
(docs/operations.md). ``csa keys`` does the same from the command line (server/cli.py); both
go through ``server/services/keys.py`` and ``server/services/audit.py``."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from server.auth import AdminScope
from server.deps import DbDep
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.schemas.admin import AuditEntryOut, KeyCreate, KeyCreatedOut, KeyOut
from server.schemas.common import ERROR_RESPONSES, ParamText
from server.services import audit, keys

router = APIRouter(tags=["admin"], responses=ERROR_RESPONSES, dependencies=[AdminScope])


@router.post(
    "/keys",
    response_model=KeyCreatedOut,
    status_code=status.HTTP_201_CREATED,
    responses={409: ERROR_RESPONSES[422]},
    description="A new key; the answer holds the key itself, the only time it is shown (only its "
    "sha256 is stored).",
)
def make_key(body: KeyCreate, db: DbDep) -> KeyCreatedOut:
    row, key = keys.create_key(db, body.name, body.scope, body.expires_in)
    return KeyCreatedOut(**keys.key_out(row).model_dump(), key=key)


@router.get("/keys", response_model=list[KeyOut], responses=PAGE_RESPONSES)
def list_keys(
    db: DbDep, response: Response, pages: PageDep, include_revoked: bool = True
) -> list[KeyOut]:
    """The database's keys by id (the settings' keys are not listed), a page at a time."""
    rows = page(db, keys.keys_query(include_revoked), pages, response, keys.ORDER)
    return [keys.key_out(k) for k in rows]


@router.post(
    "/keys/{key_ref}/revoke",
    response_model=KeyOut,
    summary="revoke a key by name or prefix (effective at its next request)",
)
def revoke(key_ref: Annotated[ParamText, "name or prefix"], db: DbDep) -> KeyOut:
    return keys.key_out(keys.revoke_key(db, key_ref))


@router.get("/audit", response_model=list[AuditEntryOut], responses=PAGE_RESPONSES)
def audit_log(
    db: DbDep,
    response: Response,
    pages: PageDep,
    key_name: Annotated[
        ParamText | None, Query(max_length=64, description="only this key's entries")
    ] = None,
    method: Annotated[
        ParamText | None, Query(max_length=8, description="only this method (POST, DELETE)")
    ] = None,
) -> list[AuditEntryOut]:
    """The write requests, newest first, a page at a time: who, what, when and the status code."""
    query = audit.audit_query(key_name, method)
    rows = page(db, query, pages, response, audit.ORDER, descending=True)
    return [AuditEntryOut.model_validate(e) for e in rows]
