"""Request dependencies: the shared services, a database session, the API key."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from server.errors import invalid
from server.services import Services


def get_services(request: Request) -> Services:
    return request.app.state.services


def get_db(services: Annotated[Services, Depends(get_services)]) -> Iterator[Session]:
    """A session per request; routes commit what they change, anything else is rolled back."""
    session = services.sessions()
    try:
        yield session
    finally:
        session.rollback()
        session.close()


ServicesDep = Annotated[Services, Depends(get_services)]
DbDep = Annotated[Session, Depends(get_db)]


async def refuse_unknown_form_parts(request: Request) -> None:
    """Refuse a multipart form carrying a part the route does not read (422 naming it and the
    parts the route takes, read from the route's own parameters): FastAPI would drop it
    silently, so a misspelt optional part (``label`` for ``labels``) would store a frame
    without its labels. A part sent twice is refused too: FastAPI would keep the last one and
    drop the other without a word."""
    allowed = {param.alias for param in request.scope["route"].dependant.body_params}
    form = await request.form()  # parsed once per request; the route's File/Form reuse it
    counts = Counter(key for key, _ in form.multi_items())
    unknown = sorted(key for key in counts if key not in allowed)
    if unknown:
        raise invalid(
            unknown[0], f"unknown form part (this route takes {', '.join(sorted(allowed))})"
        )
    repeated = sorted(key for key, n in counts.items() if n > 1)
    if repeated:
        raise invalid(repeated[0], "form part sent more than once (send each part once)")


FormPartsChecked = Depends(refuse_unknown_form_parts)
