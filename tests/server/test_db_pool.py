"""The database connection pool under load (docs/operations.md "Database connections"): a
request that cannot get a connection in time is a 503 ``database_busy``, and an ``async`` route
that waits for one does so in a worker thread, never on the event loop (which would stall
every other request of the process until a connection came back)."""

from __future__ import annotations

import threading
from pathlib import Path

import httpx
import pytest

from tests.server.conftest import API_KEY, start_server, test_settings


@pytest.fixture
def one_connection(tmp_path):
    """A server whose pool holds a single connection, and a way to take it away."""

    servers = []

    def make(timeout: float):
        settings = test_settings(
            tmp_path / "data",
            embedded_worker=False,
            db_pool_size=1,
            db_max_overflow=0,
            db_pool_timeout=timeout,
        )
        servers.append(start_server(settings))
        return servers[-1]

    yield make
    for live in servers:
        live.stop()


def test_engine_pool_follows_the_settings(tmp_path: Path) -> None:
    from server.services import open_services

    services = open_services(
        test_settings(tmp_path, db_pool_size=3, db_max_overflow=4, db_pool_timeout=2.5)
    )
    try:
        pool = services.engine.pool
        assert (pool.size(), pool._max_overflow, pool._timeout) == (3, 4, 2.5)
    finally:
        services.close()


def test_a_request_without_a_free_connection_is_503_database_busy(one_connection) -> None:
    live = one_connection(timeout=0.3)
    http = httpx.Client(base_url=live.url, headers={"X-API-Key": API_KEY}, timeout=30)
    assert http.get("/api/v1/scenes").status_code == 200
    held = live.services.engine.connect()  # the pool's only connection
    try:
        r = http.get("/api/v1/scenes")
        assert r.status_code == 503, r.text
        assert r.json()["error"]["code"] == "database_busy"
        assert r.headers["Retry-After"] == "1"
    finally:
        held.close()
    assert http.get("/api/v1/scenes").status_code == 200  # served again once one is free
    http.close()


def test_an_upload_waiting_for_a_connection_leaves_the_event_loop_serving(
    one_connection, synth_scene: Path
) -> None:
    """While a frame upload (an ``async`` route) waits for the pool's only connection, a route
    that needs no database is answered; the upload completes once the connection is back, and
    both writes are in the audit log."""
    live = one_connection(timeout=120)
    http = httpx.Client(base_url=live.url, headers={"X-API-Key": API_KEY}, timeout=150)
    http.post("/api/v1/scenes", json={"name": "pool"}).raise_for_status()
    files = {
        "color": (synth_scene / "color" / "0.png").read_bytes(),
        "depth": (synth_scene / "depth" / "0.png").read_bytes(),
        "pose": (synth_scene / "pose" / "0.txt").read_bytes(),
        "intrinsics": (synth_scene / "intrinsic" / "intrinsic_color.txt").read_bytes(),
    }
    answers: list[httpx.Response] = []
    held = live.services.engine.connect()
    upload = threading.Thread(
        target=lambda: answers.append(http.post("/api/v1/scenes/pool/frames", files=files))
    )
    try:
        upload.start()
        upload.join(timeout=1.0)  # the upload is under way and waits for the connection
        probe = httpx.get(f"{live.url}/openapi.json", timeout=60)  # no database involved
        assert probe.status_code == 200
        assert upload.is_alive() and not answers, "the upload got a connection nobody returned"
    finally:
        held.close()
    upload.join(timeout=120)
    assert [r.status_code for r in answers] == [201], [r.text for r in answers]
    # Each write's audit entry needs a connection of its own: it got the pool's only one, the
    # request's session having given it back before the answer went out.
    entries = http.get("/api/v1/audit").json()
    assert {(e["path"], e["status"]) for e in entries} >= {
        ("/api/v1/scenes", 201),
        ("/api/v1/scenes/pool/frames", 201),
    }
    http.close()
