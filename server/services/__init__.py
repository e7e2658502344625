"""The service layer, and the long-lived objects the API and the workers share.

:class:`Services` holds the settings, the database and the artifact store of one process.
The modules of this package hold the queries and the operations on each resource (scenes,
frames, model versions, NeRFs, continual metrics, jobs, keys, the audit log, the service's
status): plain functions of a database session (and the settings or the artifact store where
they need them) that raise the service's own errors (``server/errors.py``), never HTTP ones.
The REST routers (``server/routers``) and the dashboard (``server/ui``) call them; neither
builds a query (docs/architecture.md "The service").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from server.artifacts import ArtifactStore
from server.db.migrate import upgrade_to_head
from server.db.session import make_engine, make_sessionmaker
from server.keys import Principal, settings_principals
from server.settings import Settings

log = logging.getLogger(__name__)


@dataclass
class Services:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: ArtifactStore
    api_keys: list[str] = field(default_factory=list)
    # sha256 -> settings key (admin)
    key_principals: dict[str, Principal] = field(default_factory=dict)

    def set_settings_keys(self, keys: list[str], generated: bool) -> None:
        """The settings' keys (``server/auth.py``), admin keys that live outside the database."""
        self.api_keys = list(keys)
        self.key_principals = settings_principals(self.api_keys, generated)

    def close(self) -> None:
        self.engine.dispose()


def open_services(settings: Settings) -> Services:
    """Connect to the database (migrating it when configured) and open the artifact store."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = make_engine(
        settings.resolved_database_url,
        pool_size=settings.db_pool_size,
        max_overflow=settings.db_max_overflow,
        pool_timeout=settings.db_pool_timeout,
    )
    if settings.migrate_on_start:
        upgrade_to_head(engine)
    store = ArtifactStore(settings.resolved_artifact_dir)
    settings.resolved_work_dir.mkdir(parents=True, exist_ok=True)
    return Services(
        settings=settings, engine=engine, sessions=make_sessionmaker(engine), store=store
    )
