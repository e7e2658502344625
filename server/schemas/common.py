"""Shapes shared by several resources."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StringConstraints,
)

# A scene or model named by id (digits) or by name.
Ref = Annotated[str, StringConstraints(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")] | Annotated[int, Field(ge=1, le=2**62)]

# Names contain a non-digit so that they never look like ids (all-digit references are ids).
Name = Annotated[
    str,
    StringConstraints(min_length=1, max_length=128, pattern=r"^(?:[A-Za-z][A-Za-z0-9_.-]*|[0-9]+[A-Za-z_.-][A-Za-z0-9_.-]*)$"),
]


def _as_utc(value: dt.datetime) -> dt.datetime:
    return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


# The database keeps naive UTC; answers carry the zone (RFC 3339).
Timestamp = Annotated[dt.datetime, AfterValidator(_as_utc)]

# A JSON column that may be NULL in the database and is answered as ``{}``.
JsonObject = Annotated[dict[str, Any], BeforeValidator(lambda v: {} if v is None else v)]


class RecordOut(BaseModel):
    """An answer read off a database row by attribute name (``Model.model_validate(row)``)."""

    model_config = ConfigDict(from_attributes=True)


class ErrorDetail(BaseModel):
    code: str
    message: str
    field: str | None = None


class ErrorBody(BaseModel):
    """Every error answer: ``{"error": {"code", "message", "field"}}``."""

    error: ErrorDetail


class IntrinsicsIn(BaseModel):
    """Pinhole camera of an image of ``width`` x ``height`` pixels."""

    model_config = ConfigDict(extra="forbid")

    fx: float = Field(gt=0, allow_inf_nan=False)
    fy: float = Field(gt=0, allow_inf_nan=False)
    cx: float = Field(allow_inf_nan=False, ge=-1e6, le=1e6)
    cy: float = Field(allow_inf_nan=False, ge=-1e6, le=1e6)
    width: int = Field(ge=1, le=8192)
    height: int = Field(ge=1, le=8192)


class IntrinsicsOut(BaseModel):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


ERROR_RESPONSES: dict[int | str, dict] = {
    400: {"model": ErrorBody, "description": "malformed body (not JSON, broken multipart)"},
    401: {"model": ErrorBody, "description": "missing or invalid API key"},
    404: {"model": ErrorBody, "description": "not found"},
    422: {"model": ErrorBody, "description": "invalid input; `field` names the culprit"},
}
