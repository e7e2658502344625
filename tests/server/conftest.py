"""Fixtures of the service tests: real uvicorn servers on 127.0.0.1 with a temporary database
and artifact folder, a client, and tiny synthetic scene folders.

Tests that touch the database run on both backends with ``pytestmark = both_backends``: a
SQLite file in the test's folder, and a fresh database on a real PostgreSQL server
(``tests/pg.py``). Without a PostgreSQL server those runs fail under CI (``CI=true``) and are
skipped elsewhere.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from client import CSAClient
from server.app import create_app
from server.jobs.kinds import JobKind
from server.jobs.phases import ApiNode, Compute
from server.schemas.jobs import EvaluateParams
from server.settings import Settings
from tests.pg import PostgresDatabases, PostgresUnavailable, in_ci, open_postgres

API_KEY = "test-key-0123456789"
SCENE_SIZE = (40, 30)
BACKENDS = ("sqlite", "postgresql")

# The module's tests run once per backend, each with its own server or services.
both_backends = pytest.mark.parametrize("db_backend", BACKENDS, indirect=True, scope="module")


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresDatabases]:
    """The PostgreSQL server of this test run (see tests/pg.py); its databases are dropped at the
    end."""
    try:
        databases = open_postgres()
    except PostgresUnavailable as e:
        if in_ci():
            pytest.fail(f"PostgreSQL is required in CI: {e}", pytrace=False)
        pytest.skip(f"no PostgreSQL server: {e}")
    yield databases
    databases.close()


@pytest.fixture(scope="session")
def db_backend(request) -> str:
    """``sqlite`` unless a module parametrizes it (``both_backends``)."""
    return getattr(request, "param", "sqlite")


def database_url(request: pytest.FixtureRequest, backend: str) -> str | None:
    """A new empty database of ``backend``; None for SQLite (a file in the settings' data
    folder)."""
    if backend == "sqlite":
        return None
    if backend == "postgresql":
        return request.getfixturevalue("postgres").create()
    raise ValueError(f"unknown database backend {backend!r}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_settings(data_dir: Path, **overrides: object) -> Settings:
    """Settings for a test server: fast polling and short leases, one API key."""
    values: dict[str, object] = {
        # Explicit values win over CSA_* variables and .env, so tests never touch a real service.
        "data_dir": data_dir,
        "database_url": None,
        "artifact_dir": None,
        "work_dir": None,
        "embedded_worker": True,
        "public_docs": True,
        "api_keys": [API_KEY],
        "worker_poll_seconds": 0.1,
        "heartbeat_seconds": 0.3,
        "lease_seconds": 3.0,
        "sse_poll_seconds": 0.1,
        "torch_threads": 1,
        "device": "cpu",
    }
    values.update(overrides)
    return Settings(_env_file=None, **values)


test_settings.__test__ = False  # a helper, not a test


@dataclass
class LiveServer:
    url: str
    settings: Settings
    server: uvicorn.Server
    thread: threading.Thread

    @property
    def services(self):
        return self.server.config.app.state.services

    def client(self, api_key: str | None = API_KEY, timeout: float = 30.0) -> CSAClient:
        return CSAClient(self.url, api_key=api_key if api_key is not None else "", timeout=timeout)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=60)


def start_server(settings: Settings) -> LiveServer:
    """A real uvicorn server in a thread, bound to 127.0.0.1 on a free port."""
    port = free_port()
    app = create_app(settings)
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    thread = threading.Thread(target=server.run, name=f"uvicorn-{port}", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("test server did not start")
        time.sleep(0.02)
    return LiveServer(f"http://127.0.0.1:{port}", settings, server, thread)


@pytest.fixture(scope="module")
def api_server(tmp_path_factory) -> Iterator[LiveServer]:
    """A server without a worker (requests only), with small upload limits."""
    settings = test_settings(
        tmp_path_factory.mktemp("api"),
        embedded_worker=False,
        max_frame_upload_bytes=200_000,
        max_archive_bytes=2_000_000,
        max_archive_members=200,
    )
    live = start_server(settings)
    yield live
    live.stop()


@pytest.fixture
def client(api_server: LiveServer) -> Iterator[CSAClient]:
    with api_server.client() as c:
        yield c


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory) -> Path:
    """A tiny procedural room: 8 frames of 40x30 with NYU40 ground truth."""
    from csa_core.data.synth import synthesize

    (path,) = synthesize(
        tmp_path_factory.mktemp("synth"),
        scenes=1,
        frames=8,
        size=SCENE_SIZE,
        family="office",
        seed=3,
    )
    return path


# -- job kinds of tests ----------------------------------------------------------------------


@dataclass
class ParamsInputs:
    """A test kind's Inputs: its job's parameters."""

    params: dict[str, Any]


@dataclass
class ResultOutputs:
    """A test kind's Outputs: the job's result."""

    result: dict[str, Any]


def gather_params(session, params: dict[str, Any], node: ApiNode) -> ParamsInputs:
    return ParamsInputs(dict(params))


def register_result(session, outputs: ResultOutputs, node: ApiNode) -> dict[str, Any]:
    return outputs.result


def job_kind(name: str, compute: Compute) -> JobKind:
    """A job kind for tests: its Inputs are its parameters, ``compute`` makes its result."""
    return JobKind(
        name,
        "test job",
        EvaluateParams,
        (),
        lambda s, p, j: ({}, None),
        gather_params,
        compute,
        register_result,
    )
