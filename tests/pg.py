"""A PostgreSQL server for the tests, and fresh databases on it.

``CSA_TEST_POSTGRES`` chooses the server:

* unset or ``auto``: the one listening on 127.0.0.1:5432 (user ``postgres``, trust
  authentication) when it answers, otherwise a private server started here;
* ``start``: always a private server: ``initdb`` and ``pg_ctl`` of the installed PostgreSQL
  (on PATH or in Debian's ``/usr/lib/postgresql/<version>/bin``) into a temporary folder, on a
  free port of 127.0.0.1, as an unprivileged user when the tests run as root (PostgreSQL
  refuses to run as root), stopped and removed at the end;
* a URL such as ``postgresql://user:password@host:5432/postgres``: that server.

Each test run names its databases with a unique prefix (process id and a random token), creates
one empty database per test server or fixture and drops them all at the end, so runs never see
each other's rows and leave nothing behind.
"""

from __future__ import annotations

import glob
import os
import pwd
import secrets
import shutil
import socket
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy.engine import URL, make_url

DEFAULT_URL = "postgresql://postgres@127.0.0.1:5432/postgres"
ENV = "CSA_TEST_POSTGRES"
_START_TIMEOUT_S = 60


def in_ci() -> bool:
    """Under CI (``CI=true``) a missing PostgreSQL fails the tests that need it instead of
    skipping them."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


class PostgresUnavailable(RuntimeError):
    """No PostgreSQL server could be reached or started; the message says why."""


def _connect(url: URL, timeout: int = 5):
    import psycopg

    return psycopg.connect(
        host=url.host,
        port=url.port or 5432,
        user=url.username,
        password=url.password,
        dbname=url.database or "postgres",
        connect_timeout=timeout,
        autocommit=True,
    )


def _answers(url: URL) -> str | None:
    """None when the server answers ``SELECT 1``, else the reason."""
    try:
        with _connect(url, timeout=3) as conn:
            conn.execute("SELECT 1")
        return None
    except Exception as e:  # any driver or network error means "not usable"
        return f"{type(e).__name__}: {str(e).strip()}"


def server_binaries() -> Path | None:
    """The folder holding ``initdb`` and ``pg_ctl``: on PATH, else the newest Debian install."""
    on_path = shutil.which("pg_ctl")
    if on_path and shutil.which("initdb"):
        return Path(on_path).resolve().parent
    found = [
        Path(p).parent
        for p in glob.glob("/usr/lib/postgresql/*/bin/pg_ctl")
        if (Path(p).parent / "initdb").is_file()
    ]
    found.sort(key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0)
    return found[-1] if found else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_as() -> pwd.struct_passwd | None:
    """The account to run the server as: none (ourselves) unless we are root."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            return pwd.getpwnam(name)
        except KeyError:
            continue
    raise PostgresUnavailable(
        "running as root and neither a 'postgres' nor a 'nobody' account exists to run PostgreSQL"
    )


@dataclass
class PrivateServer:
    """A PostgreSQL cluster in a temporary folder, for this test run only."""

    folder: Path
    bin_dir: Path
    port: int
    user: pwd.struct_passwd | None

    @property
    def url(self) -> URL:
        return URL.create(
            "postgresql+psycopg",
            username="postgres",
            host="127.0.0.1",
            port=self.port,
            database="postgres",
        )

    def _run(self, *args: str, timeout: float) -> subprocess.CompletedProcess:
        kw = (
            {"user": self.user.pw_uid, "group": self.user.pw_gid, "extra_groups": []}
            if self.user
            else {}
        )
        env = {
            "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
            "LC_ALL": "C.UTF-8",
            "LANG": "C.UTF-8",
        }
        return subprocess.run(
            args,
            cwd=self.folder,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
            **kw,
        )

    @classmethod
    def start(cls) -> PrivateServer:
        bin_dir = server_binaries()
        if bin_dir is None:
            raise PostgresUnavailable(
                "no initdb/pg_ctl found (install Debian's 'postgresql' package)"
            )
        user = _run_as()
        folder = Path(tempfile.mkdtemp(prefix="csa-test-pg-"))
        if user is not None:
            os.chown(folder, user.pw_uid, user.pw_gid)
        server = cls(folder, bin_dir, _free_port(), user)
        try:
            init = server._run(
                str(bin_dir / "initdb"),
                "-D",
                "data",
                "-U",
                "postgres",
                "--auth=trust",
                "--encoding=UTF8",
                "--no-sync",
                timeout=_START_TIMEOUT_S,
            )
            if init.returncode != 0:
                raise PostgresUnavailable(f"initdb failed: {init.stderr.strip()[-2000:]}")
            options = (
                f"-p {server.port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync=off -c "
                "full_page_writes=off"
            )
            started = server._run(
                str(bin_dir / "pg_ctl"),
                "-D",
                "data",
                "-l",
                "server.log",
                "-o",
                options,
                "-w",
                "-t",
                str(_START_TIMEOUT_S),
                "start",
                timeout=_START_TIMEOUT_S + 10,
            )
            if started.returncode != 0:
                log = (
                    (folder / "server.log").read_text(errors="replace")
                    if (folder / "server.log").is_file()
                    else ""
                )
                raise PostgresUnavailable(
                    f"pg_ctl start failed: {started.stderr.strip()[-1000:]} {log[-1000:]}"
                )
        except BaseException:
            server.stop()
            raise
        return server

    def stop(self) -> None:
        if (self.folder / "data" / "postmaster.pid").is_file():
            self._run(
                str(self.bin_dir / "pg_ctl"),
                "-D",
                "data",
                "-m",
                "fast",
                "-w",
                "stop",
                timeout=_START_TIMEOUT_S,
            )
        shutil.rmtree(self.folder, ignore_errors=True)


@dataclass
class PostgresDatabases:
    """Creates empty databases on one server and drops them all in :meth:`close`."""

    admin_url: URL
    server: PrivateServer | None = None
    prefix: str = field(default_factory=lambda: f"csa_test_{os.getpid()}_{secrets.token_hex(4)}")
    created: list[str] = field(default_factory=list)

    def create(self) -> str:
        """A new empty database; returns its SQLAlchemy URL (psycopg driver)."""
        name = f"{self.prefix}_{len(self.created)}"
        with _connect(self.admin_url) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        self.created.append(name)
        return self.admin_url.set(drivername="postgresql+psycopg", database=name).render_as_string(
            hide_password=False
        )

    def close(self) -> None:
        try:
            with _connect(self.admin_url) as conn:
                for name in self.created:
                    conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
            self.created.clear()
        finally:
            if self.server is not None:
                self.server.stop()


def open_postgres() -> PostgresDatabases:
    """The server ``CSA_TEST_POSTGRES`` asks for; raises :class:`PostgresUnavailable` with the
    reasons when there is none."""
    choice = os.environ.get(ENV, "auto").strip() or "auto"
    try:
        import psycopg  # noqa: F401
    except ImportError:
        raise PostgresUnavailable(
            "the psycopg driver is not installed (pip install -e '.[server]')"
        ) from None
    if choice not in ("auto", "start"):
        url = make_url(choice)
        reason = _answers(url)
        if reason is not None:
            raise PostgresUnavailable(f"{ENV}={url.render_as_string()} does not answer: {reason}")
        return PostgresDatabases(url)
    reasons = []
    if choice == "auto":
        url = make_url(DEFAULT_URL)
        reason = _answers(url)
        if reason is None:
            return PostgresDatabases(url)
        reasons.append(f"{url.host}:{url.port} does not answer ({reason})")
    try:
        server = PrivateServer.start()
    except PostgresUnavailable as e:
        raise PostgresUnavailable("; ".join([*reasons, str(e)])) from None
    return PostgresDatabases(server.url, server=server)
