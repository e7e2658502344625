"""Pages of the list routes (scenes, a scene's frames, model versions): ``limit`` rows over a
stable order, and the number of rows of the whole list in the ``X-Total-Count`` header, so that
no answer grows with what a client has stored and a client knows when there is more to read.

A page starts at ``offset`` rows into the list, or right after a row named by ``after``: a
cursor, the opaque token of the row's sort key that a full page's ``Link: <...>; rel="next"``
header carries. Following the cursors reads every row that exists from start to end exactly
once even while other clients add or delete rows (an offset shifts then, and a row is missed or
read twice); ``CSAClient`` follows them."""

from __future__ import annotations

import base64
import binascii
import json
from collections.abc import Sequence
from typing import Annotated, Any

from fastapi import Depends, Query, Request, Response
from sqlalchemy import Select, func, select, tuple_
from sqlalchemy.orm import InstrumentedAttribute, Session

from server.db.models import MAX_ID
from server.errors import invalid, is_utf8_text

# The most rows one answer holds, and the default: a list that fitted in one answer before
# pages existed still does, up to this many rows.
MAX_LIMIT = 1000
TOTAL_COUNT_HEADER = "X-Total-Count"

Limit = Annotated[
    int,
    Query(
        ge=1,
        le=MAX_LIMIT,
        description=f"rows in this answer, 1 to {MAX_LIMIT} (default {MAX_LIMIT})",
    ),
]
# Row ids are 32-bit (MAX_ID), so no list holds more rows; the bound also keeps the number
# inside a 64-bit SQL integer on every backend (a 422, never a database error).
Offset = Annotated[int, Query(ge=0, le=MAX_ID, description="rows of the list to skip (default 0)")]
After = Annotated[
    str | None,
    Query(
        max_length=512,
        description=(
            'start after this cursor (from the Link rel="next" header of the previous page); not '
            "with offset"
        ),
    ),
]

# The header in the OpenAPI document of a paged route (merged into its 200 answer).
PAGE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "headers": {
            TOTAL_COUNT_HEADER: {
                "description": "rows in the whole list, all pages together",
                "required": True,
                "schema": {"type": "integer", "minimum": 0},
            },
            "Link": {
                "description": (
                    'rel="next": the URL of the next page (a cursor in ``after``), sent with every '
                    "full page"
                ),
                "schema": {"type": "string"},
            },
        }
    }
}


class PageQuery:
    """The page a list request asks for: ``limit``, and ``offset`` or ``after``."""

    def __init__(
        self, request: Request, limit: Limit = MAX_LIMIT, offset: Offset = 0, after: After = None
    ):
        if after is not None and offset:
            raise invalid(
                "offset", "cannot be combined with after (the cursor says where the page starts)"
            )
        self.request, self.limit, self.offset, self.after = request, limit, offset, after


PageDep = Annotated[PageQuery, Depends()]


def encode_cursor(values: Sequence[int | str]) -> str:
    """The opaque cursor of a row's sort key: URL-safe base64 of its JSON, without padding."""
    return (
        base64.urlsafe_b64encode(json.dumps(list(values), separators=(",", ":")).encode())
        .decode()
        .rstrip("=")
    )


def decode_cursor(cursor: str, types: Sequence[type]) -> list[int | str]:
    """The sort key in ``cursor``, checked against the key's column ``types`` (int or str);
    a 422 naming ``after`` for anything this server did not give out."""
    bad = invalid(
        "after", "not a cursor of this list (pass the one in the previous page's Link header)"
    )
    try:
        values = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
    except (binascii.Error, ValueError, UnicodeDecodeError):
        raise bad from None
    if not isinstance(values, list) or len(values) != len(types):
        raise bad
    for v, t in zip(values, types, strict=True):
        # bool is an int to Python, not to a sort key; ints stay inside the ids' 32 bits.
        if type(v) is not t or (t is int and not -MAX_ID - 1 <= v <= MAX_ID):
            raise bad
        # JSON escapes can spell text no column holds: a lone surrogate ("\ud800"), which
        # cannot be encoded for the database, or a NUL character.
        if t is str and ("\x00" in v or not is_utf8_text(v)):
            raise bad
    return values


def page(
    db: Session,
    query: Select,
    pages: PageQuery,
    response: Response,
    keys: Sequence[InstrumentedAttribute],
    descending: bool = False,
) -> list[Any]:
    """The rows of ``pages`` from ``query``, which must order its rows by ``keys`` (ascending,
    or descending with ``descending``; together unique, so that pages neither overlap nor skip);
    sets ``X-Total-Count`` on ``response``, and a ``Link`` to the next page when this one is
    full."""
    total = db.scalar(select(func.count()).select_from(query.order_by(None).subquery()))
    response.headers[TOTAL_COUNT_HEADER] = str(total or 0)
    if pages.after is not None:
        values = decode_cursor(pages.after, [k.type.python_type for k in keys])
        if len(keys) == 1:
            query = query.where(keys[0] < values[0] if descending else keys[0] > values[0])
        else:
            query = query.where(
                tuple_(*keys) < tuple_(*values) if descending else tuple_(*keys) > tuple_(*values)
            )
    rows = list(db.scalars(query.limit(pages.limit).offset(pages.offset)))
    if len(rows) == pages.limit:
        cursor = encode_cursor([getattr(rows[-1], k.key) for k in keys])
        url = pages.request.url.remove_query_params(["offset", "after"]).include_query_params(
            after=cursor
        )
        response.headers["Link"] = f'<{url}>; rel="next"'
    return rows
