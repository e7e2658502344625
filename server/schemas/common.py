"""Shapes shared by several resources."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from typing import Annotated, Any

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StringConstraints,
)
from pydantic_core import PydanticCustomError

from csa_core.data.camera import MAX_SIZE_PX, Intrinsics, check_intrinsics, check_pose
from csa_core.errors import CSAInputError
from server.db.models import MAX_ID

# A row id in a path, query or body: the database's 32-bit integer ids.
RowId = Annotated[int, Field(ge=1, le=MAX_ID)]

# A scene or model named by id (digits) or by name.
Ref = (
    Annotated[
        str,
        StringConstraints(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"),
    ]
    | RowId
)

# Names contain a non-digit so that they never look like ids (all-digit references are ids).
Name = Annotated[
    str,
    StringConstraints(
        min_length=1,
        max_length=128,
        pattern=r"^(?:[A-Za-z][A-Za-z0-9_.-]*|[0-9]+[A-Za-z_.-][A-Za-z0-9_.-]*)$",
    ),
]


def _as_utc(value: dt.datetime) -> dt.datetime:
    return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


# Free text: anything but NUL characters, which PostgreSQL's text columns cannot hold.
PlainText = Annotated[str, StringConstraints(pattern=r"^[^\x00]*$")]

NUL_PROBLEM = "must not contain a NUL character (%00)"


def _without_nul(value: str) -> str:
    if "\x00" in value:
        raise PydanticCustomError("nul_character", NUL_PROBLEM)
    return value


# A name, reference or filter in a path or query string: anything but a NUL character, which
# no row holds (and PostgreSQL's text cannot even be compared with), refused with a 422 naming
# the parameter on every database alike.
ParamText = Annotated[str, AfterValidator(_without_nul)]

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


def core_rule(kind: str, check: Callable[[Any], object]) -> AfterValidator:
    """A validator that applies a csa_core check to a field: the core's :class:`CSAInputError`
    becomes a validation error of that field (a 422 naming it, see server/errors.py)."""

    def run(value: Any) -> Any:
        try:
            check(value)
        except CSAInputError as e:
            raise PydanticCustomError(kind, e.problem) from None
        return value

    return AfterValidator(run)


# A camera-to-world pose in a request body, checked by the core's rule for poses
# (csa_core.data.camera.check_pose): finite, rigid (rotation and translation only), bounded.
Pose = Annotated[
    list[
        Annotated[
            list[Annotated[float, Field(allow_inf_nan=False)]], Field(min_length=4, max_length=4)
        ]
    ],
    Field(
        min_length=4,
        max_length=4,
        description=(
            "4x4 camera-to-world matrix (rows, metres, OpenCV axes): a rigid transform, "
            "last row 0 0 0 1"
        ),
    ),
    core_rule("pose", lambda rows: check_pose(np.asarray(rows, dtype=np.float64), "pose")),
]


class IntrinsicsIn(BaseModel):
    """Pinhole camera of an image of ``width`` x ``height`` pixels (requests take :data:`Camera`,
    which adds the core's rule for cameras, ``csa_core.data.camera.check_intrinsics``)."""

    model_config = ConfigDict(extra="forbid")

    fx: float = Field(gt=0, allow_inf_nan=False)
    fy: float = Field(gt=0, allow_inf_nan=False)
    cx: float = Field(allow_inf_nan=False)
    cy: float = Field(allow_inf_nan=False)
    width: int = Field(ge=1, le=MAX_SIZE_PX)
    height: int = Field(ge=1, le=MAX_SIZE_PX)

    def camera(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


# A camera in a request body; sane for its image size by the core's rule for cameras.
Camera = Annotated[
    IntrinsicsIn,
    core_rule("intrinsics", lambda intr: check_intrinsics(intr.camera(), "intrinsics")),
]


class IntrinsicsOut(BaseModel):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


ERROR_RESPONSES: dict[int | str, dict] = {
    400: {"model": ErrorBody, "description": "malformed body (not JSON, broken multipart)"},
    401: {"model": ErrorBody, "description": "missing, invalid, revoked or expired API key"},
    403: {
        "model": ErrorBody,
        "description": (
            "the key's scope does not reach this route or scene "
            "(the message names the scope needed)"
        ),
    },
    404: {"model": ErrorBody, "description": "not found"},
    422: {"model": ErrorBody, "description": "invalid input; `field` names the culprit"},
}
