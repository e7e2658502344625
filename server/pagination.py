"""Pages of the list routes (scenes, a scene's frames, model versions): ``limit`` and ``offset``
query parameters over a stable order, and the number of rows of the whole list in the
``X-Total-Count`` header, so that no answer grows with what a client has stored and a client
knows when there is more to read (``CSAClient`` reads every page)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Query, Response
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from server.db.models import MAX_ID

# The most rows one answer holds, and the default: a list that fitted in one answer before
# pages existed still does, up to this many rows.
MAX_LIMIT = 1000
TOTAL_COUNT_HEADER = "X-Total-Count"

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description=f"rows in this answer, 1 to {MAX_LIMIT} (default {MAX_LIMIT})")]
# Row ids are 32-bit (MAX_ID), so no list holds more rows; the bound also keeps the number
# inside a 64-bit SQL integer on every backend (a 422, never a database error).
Offset = Annotated[int, Query(ge=0, le=MAX_ID, description="rows of the list to skip (default 0)")]

# The header in the OpenAPI document of a paged route (merged into its 200 answer).
PAGE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "headers": {
            TOTAL_COUNT_HEADER: {
                "description": "rows in the whole list, all pages together",
                "required": True,
                "schema": {"type": "integer", "minimum": 0},
            }
        }
    }
}


def page(db: Session, query: Select, limit: int, offset: int, response: Response) -> list[Any]:
    """Rows ``offset`` to ``offset + limit`` of ``query`` (which must order its rows by a
    unique key, so that pages neither overlap nor skip); sets ``X-Total-Count`` on ``response``."""
    total = db.scalar(select(func.count()).select_from(query.order_by(None).subquery()))
    response.headers[TOTAL_COUNT_HEADER] = str(total or 0)
    return list(db.scalars(query.limit(limit).offset(offset)))
