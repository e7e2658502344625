"""The tests' own PostgreSQL server (tests/pg.py), the fallback when none answers on
127.0.0.1:5432: started from initdb and pg_ctl as an unprivileged account, it serves fresh
databases and is gone, folder and databases, after ``close``."""

from __future__ import annotations

import os

import pytest
from sqlalchemy import create_engine, text

from tests.pg import PostgresDatabases, PrivateServer, in_ci, server_binaries


def test_a_private_server_serves_fresh_databases_and_leaves_nothing() -> None:
    if server_binaries() is None:
        if in_ci():
            pytest.fail(
                "PostgreSQL's initdb/pg_ctl are missing (.ci/run installs Debian's postgresql "
                "package)"
            )
        pytest.skip("PostgreSQL's initdb/pg_ctl are not installed")
    server = PrivateServer.start()
    databases = PostgresDatabases(server.url, server=server)
    try:
        urls = [databases.create(), databases.create()]
        assert len(set(urls)) == 2 and all(
            u.startswith(
                f"postgresql+psycopg://postgres@127.0.0.1:{server.port}/{databases.prefix}_"
            )
            for u in urls
        )
        engine = create_engine(urls[0])
        with engine.begin() as conn:
            assert (
                conn.execute(
                    text("SELECT count(*) FROM pg_tables WHERE schemaname = 'public'")
                ).scalar()
                == 0
            )
            conn.execute(text("CREATE TABLE t (x int)"))
            owner = conn.execute(
                text("SELECT usename FROM pg_stat_activity WHERE pid = pg_backend_pid()")
            ).scalar()
        engine.dispose()
        assert owner == "postgres"
        data_owner = (server.folder / "data").stat().st_uid  # PostgreSQL refuses to run as root
        assert data_owner != 0 and data_owner == (
            server.user.pw_uid if server.user else os.geteuid()
        )
        admin = create_engine(server.url, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            names = set(conn.execute(text("SELECT datname FROM pg_database")).scalars())
        admin.dispose()
        assert {u.rsplit("/", 1)[1] for u in urls} <= names
    finally:
        databases.close()
    assert not server.folder.exists()
