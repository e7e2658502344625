"""The Alembic migrations create exactly the schema the ORM models describe, on SQLite and on
PostgreSQL, and downgrade back to an empty database."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from server.db.migrate import alembic_config, upgrade_to_head
from server.db.models import Base
from server.db.session import make_engine
from tests.server.conftest import both_backends, database_url

pytestmark = both_backends


def _schema_diff(engine) -> list:
    with engine.connect() as conn:
        return compare_metadata(MigrationContext.configure(conn), Base.metadata)


def test_migrations_match_the_models_and_downgrade(
    request, db_backend: str, tmp_path: Path
) -> None:
    engine = make_engine(database_url(request, db_backend) or f"sqlite:///{tmp_path / 'csa.db'}")
    assert engine.dialect.name == db_backend
    upgrade_to_head(engine)
    upgrade_to_head(engine)  # idempotent: a second start changes nothing
    assert _schema_diff(engine) == []
    assert set(inspect(engine).get_table_names()) == set(Base.metadata.tables) | {"alembic_version"}

    cfg = alembic_config()
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.downgrade(cfg, "base")
    assert set(inspect(engine).get_table_names()) <= {"alembic_version"}

    upgrade_to_head(engine)  # and up again from nothing
    assert _schema_diff(engine) == []
    engine.dispose()
