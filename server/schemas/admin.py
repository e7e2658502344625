"""API keys and the audit log, for admins (docs/operations.md)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from server.keys import Scope
from server.schemas.common import RecordOut, Timestamp


class KeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z][A-Za-z0-9_.-]*$",
        description="unique, also after revocation",
    )
    scope: Scope
    expires_in: str | None = Field(
        default=None,
        max_length=16,
        description="lifetime such as 30d, 12h, 90m or 2w (default: no expiry)",
    )


class KeyOut(RecordOut):
    id: int
    name: str
    prefix: str = Field(
        description="the key's first characters; the key itself is never shown again"
    )
    scope: Scope
    state: str = Field(description="active, expired or revoked")
    created_at: Timestamp
    expires_at: Timestamp | None
    last_used_at: Timestamp | None = Field(description="to the minute")
    revoked_at: Timestamp | None


class KeyCreatedOut(KeyOut):
    key: str = Field(description="the API key: shown in this answer only, store it now")


class AuditEntryOut(RecordOut):
    id: int
    created_at: Timestamp
    key_name: str
    scope: str
    method: str
    route: str
    path: str
    ids: dict[str, Any]
    status: int
