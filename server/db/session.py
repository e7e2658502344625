"""Database engine and sessions for any SQLAlchemy URL (SQLite by default)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker


def make_engine(
    url: str,
    pool_size: int | None = None,
    max_overflow: int | None = None,
    pool_timeout: float | None = None,
) -> Engine:
    """An engine; SQLite files get WAL journaling and a busy timeout so that the API, the
    executor's threads (and API replicas on one host) can share one database file. A PostgreSQL URL
    without a driver (``postgresql://...``) uses psycopg 3, the driver the server extra installs.

    ``pool_size``, ``max_overflow`` and ``pool_timeout`` size the connection pool (SQLAlchemy's
    defaults where ``None``; an in-memory SQLite database has no pool to size): a caller that
    waits ``pool_timeout`` seconds for a connection gets ``sqlalchemy.exc.TimeoutError``."""
    pool = {
        key: value
        for key, value in (
            ("pool_size", pool_size),
            ("max_overflow", max_overflow),
            ("pool_timeout", pool_timeout),
        )
        if value is not None
    }
    parsed = make_url(url)
    if parsed.drivername == "postgresql":
        parsed = parsed.set(drivername="postgresql+psycopg")
    if parsed.get_backend_name() != "sqlite":
        # pool_pre_ping: a pooled connection that a database restart broke is replaced when it
        # is next taken, so the service recovers by itself (docs/operations.md "Database
        # restarts"); connect_timeout bounds a request's wait for a database that is away.
        connect_args = {"connect_timeout": 10} if parsed.get_backend_name() == "postgresql" else {}
        return create_engine(parsed, pool_pre_ping=True, connect_args=connect_args, **pool)
    if parsed.database and parsed.database != ":memory:":
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    else:
        pool = {}
    engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30}, **pool)

    @event.listens_for(engine, "connect")
    def _sqlite_pragmas(dbapi_conn, _record) -> None:  # pragma: no cover - trivial
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute("PRAGMA busy_timeout=30000")
        cur.close()

    return engine


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(bind=engine, expire_on_commit=False)


def release_connection(session: Session) -> None:
    """End ``session``'s transaction so that its connection goes back to the pool; what it
    loaded stays loaded (the sessions here do not expire on commit). For code that read what
    it needs and goes on to wait (an upload's body, a render's turn) without the database."""
    if session.in_transaction():
        session.commit()


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session that commits when the block succeeds and rolls back when it raises."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()
