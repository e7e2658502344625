"""Request dependencies: the shared services, a database session, the API key."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from typing import Annotated, TypeVar

from fastapi import Depends, Request
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from server.db.session import release_connection
from server.errors import invalid
from server.services import Services

T = TypeVar("T")


def get_services(request: Request) -> Services:
    return request.app.state.services


def get_db(services: Annotated[Services, Depends(get_services)]) -> Iterator[Session]:
    """A session per request; routes commit what they change, anything else is rolled back.

    It is closed as soon as the route function returns, before the answer is serialised and
    sent (``scope="function"`` below), so its connection is back in the pool while the audit
    log records the request (``server/audit.py``, which needs one of its own): a write never
    holds two connections at once, and a full pool cannot make every write wait for a second.
    Closing keeps what the route loaded readable for the answer (only a rollback would expire
    it); an error rolls the transaction back first."""
    session = services.sessions()
    try:
        yield session
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


ServicesDep = Annotated[Services, Depends(get_services)]
DbDep = Annotated[Session, Depends(get_db, scope="function")]


async def read_in_thread(db: Session, read: Callable[..., T], *args: object) -> T:
    """``read(db, *args)`` in a worker thread, then ``db``'s connection back to the pool (what
    it loaded stays loaded). For ``async`` routes: a database call on the event loop would,
    with every pooled connection taken, stall all requests of the process for the pool's
    timeout; and a connection kept while the route awaits a body or a render's turn is one
    fewer for every other request."""

    def call() -> T:
        try:
            return read(db, *args)
        except BaseException:
            db.rollback()
            raise
        finally:
            release_connection(db)

    return await run_in_threadpool(call)


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
