"""Request dependencies: the shared services, a database session, the API key."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

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
