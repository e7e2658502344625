"""``csa backup DIR`` and ``csa restore DIR``: the database and the artifact store, consistent
with each other (docs/operations.md "Backup and restore").

The database is copied first, in one consistent snapshot: SQLite's online backup API
(``sqlite3.Connection.backup``, safe while the service writes) or ``pg_dump`` for PostgreSQL,
whose snapshot is the one the list of artifacts is read in. Then every blob that copy records
is copied, hashed on the way (a blob is named by its sha256, and never modified). Blobs are
written before the rows that record them and deleted only after their rows, so every blob the
copy records still exists unless a deletion committed meanwhile: then the backup fails, naming
it, and can be run again. ``manifest.json`` is written last; it holds the database file's
sha256 and every blob's size, and a folder without it is not a finished backup.

A restore checks the whole backup against its manifest before it touches the target, and
refuses a target that holds data unless ``force``.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import create_engine, inspect, text
from sqlalchemy.engine import URL, make_url

from server.artifacts import ArtifactStore, sha256_file
from server.settings import Settings

MANIFEST = "manifest.json"
FORMAT = 1
SQLITE_FILE = "csa.db"
PG_DUMP_FILE = "database.dump"
API_KEY_FILE = "api_key"
_CHUNK = 1 << 20


class BackupError(RuntimeError):
    """A backup or restore that cannot go on; the message names the file and the problem."""


@dataclass(frozen=True)
class BackupSummary:
    folder: Path
    database: str
    artifacts: int
    artifact_bytes: int


def _backend(url: str) -> str:
    return make_url(url).get_backend_name()


def _pg_conninfo(url: str) -> tuple[str, dict[str, str]]:
    """A libpq URL for pg_dump / pg_restore and the environment carrying its password
    (never on the command line, where other users of the host could read it)."""
    parsed = make_url(url)
    env = {**os.environ}
    if parsed.password is not None:
        env["PGPASSWORD"] = str(parsed.password)
    plain = URL.create(
        "postgresql",
        username=parsed.username,
        host=parsed.host,
        port=parsed.port,
        database=parsed.database,
    )
    return plain.render_as_string(hide_password=False), env


def _run(args: list[str], env: dict[str, str], what: str) -> None:
    try:
        done = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
    except FileNotFoundError:
        raise BackupError(
            f"{what}: {args[0]} is not installed (PostgreSQL's client programs are needed)"
        ) from None
    if done.returncode != 0:
        raise BackupError(
            f"{what} failed ({args[0]} exit {done.returncode}): {done.stderr.strip()[-1000:]}"
        )


def _copy_hashed(src: Path, dest: Path) -> tuple[str, int]:
    """Copy ``src`` to ``dest`` (through a temporary name, fsynced); returns sha256 and size."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".part")
    h, size = hashlib.sha256(), 0
    try:
        with open(src, "rb") as fin, open(tmp, "wb") as fout:
            while chunk := fin.read(_CHUNK):
                h.update(chunk)
                size += len(chunk)
                fout.write(chunk)
            fout.flush()
            os.fsync(fout.fileno())
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return h.hexdigest(), size


def _snapshot_sqlite(db_file: Path, dest: Path) -> list[tuple[str, int]]:
    if not db_file.is_file():
        raise BackupError(f"{db_file}: no database file (nothing to back up)")
    src = sqlite3.connect(db_file, timeout=30)
    out = sqlite3.connect(dest)
    try:
        with out:
            src.backup(out)
        out.execute("PRAGMA journal_mode=DELETE")  # one self-contained file
        rows = out.execute("SELECT sha256, size_bytes FROM artifacts ORDER BY sha256").fetchall()
    finally:
        out.close()
        src.close()
    return [(sha, int(size)) for sha, size in rows]


def _snapshot_postgres(url: str, dest: Path) -> list[tuple[str, int]]:
    """``pg_dump`` in the snapshot that the artifact list is read in."""
    conninfo, env = _pg_conninfo(url)
    engine = create_engine(make_url(url).set(drivername="postgresql+psycopg"))
    try:
        with engine.connect() as conn:
            conn.execute(text("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY"))
            snapshot = conn.execute(text("SELECT pg_export_snapshot()")).scalar_one()
            rows = conn.execute(
                text("SELECT sha256, size_bytes FROM artifacts ORDER BY sha256")
            ).all()
            _run(
                [
                    "pg_dump",
                    "--format=custom",
                    "--no-owner",
                    f"--snapshot={snapshot}",
                    f"--file={dest}",
                    conninfo,
                ],
                env,
                "pg_dump",
            )
            conn.rollback()
    finally:
        engine.dispose()
    return [(sha, int(size)) for sha, size in rows]


def backup(settings: Settings, folder: Path) -> BackupSummary:
    """Copy the service's database, then its blobs, into the new or empty ``folder``."""
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise BackupError(f"{folder}: not an empty folder (a backup goes into a new or empty one)")
    folder.mkdir(parents=True, exist_ok=True)
    url = settings.resolved_database_url
    kind = _backend(url)
    if kind == "sqlite":
        db_name = SQLITE_FILE
        artifacts = _snapshot_sqlite(Path(make_url(url).database or ""), folder / db_name)
    elif kind == "postgresql":
        db_name = PG_DUMP_FILE
        artifacts = _snapshot_postgres(url, folder / db_name)
    else:
        raise BackupError(f"database_url: backups support SQLite and PostgreSQL, not {kind!r}")

    store = ArtifactStore(settings.resolved_artifact_dir)
    total = 0
    for sha, size in artifacts:
        src = store.path_of(sha)
        if not src.is_file():
            raise BackupError(
                f"artifact {sha}: recorded in the database copy but its file {src} is gone "
                "(deleted during the backup, or lost: run csa doctor); run the backup again"
            )
        got, got_size = _copy_hashed(src, folder / "artifacts" / sha[:2] / sha)
        if got != sha or got_size != size:
            raise BackupError(
                f"artifact {sha}: the file {src} does not match its checksum and size ({got_size} "
                f"bytes, recorded {size}); run csa doctor"
            )
        total += size
    key_file = settings.data_dir / API_KEY_FILE
    if key_file.is_file():
        shutil.copy2(key_file, folder / API_KEY_FILE)
    manifest = {
        "format": FORMAT,
        "created_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "database": kind,
        "database_file": db_name,
        "database_sha256": sha256_file(folder / db_name),
        "artifacts": dict(artifacts),
        "api_key_file": key_file.is_file(),
    }
    tmp = folder / (MANIFEST + ".part")
    tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True))
    os.replace(tmp, folder / MANIFEST)
    return BackupSummary(folder, kind, len(artifacts), total)


def read_manifest(folder: Path) -> dict:
    path = Path(folder) / MANIFEST
    if not path.is_file():
        raise BackupError(
            f"{path}: missing (not a backup made by csa backup, or one that did not finish)"
        )
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise BackupError(f"{path}: not readable JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise BackupError(
            f"{path}: format {manifest.get('format') if isinstance(manifest, dict) else None!r}, "
            f"this version reads format {FORMAT}"
        )
    return manifest


def check_backup(folder: Path) -> dict:
    """The manifest, once the database file and every blob match it; BackupError naming the
    first file that does not."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    db_file = folder / manifest["database_file"]
    if not db_file.is_file() or sha256_file(db_file) != manifest["database_sha256"]:
        raise BackupError(
            f"{db_file}: missing or not the file the manifest records (sha256 differs)"
        )
    for sha, size in manifest["artifacts"].items():
        blob = folder / "artifacts" / sha[:2] / sha
        if not blob.is_file():
            raise BackupError(f"{blob}: missing from the backup")
        if blob.stat().st_size != size or sha256_file(blob) != sha:
            raise BackupError(f"{blob}: does not match its checksum and size (corrupt backup)")
    return manifest


def _postgres_has_tables(url: str) -> bool:
    engine = create_engine(make_url(url).set(drivername="postgresql+psycopg"))
    try:
        with engine.connect() as conn:
            return bool(inspect(conn).get_table_names())
    finally:
        engine.dispose()


def restore(settings: Settings, folder: Path, force: bool = False) -> BackupSummary:
    """Put a backup in place of the service's data (the service stopped)."""
    folder = Path(folder)
    manifest = check_backup(folder)
    url = settings.resolved_database_url
    kind = _backend(url)
    if manifest["database"] != kind:
        raise BackupError(
            f"{folder / MANIFEST}: the backup holds a {manifest['database']} database, the target "
            f"is {kind} (database_url)"
        )
    artifact_dir = settings.resolved_artifact_dir
    blobs = artifact_dir / "blobs"
    has_blobs = blobs.is_dir() and any(
        p.is_file() for d in blobs.iterdir() if d.is_dir() for p in d.iterdir()
    )
    if kind == "sqlite":
        db_file = Path(make_url(url).database or "")
        has_db = db_file.is_file()
    else:
        has_db = _postgres_has_tables(url)
    if (has_db or has_blobs) and not force:
        what = " and ".join(
            w for w, yes in (("a database", has_db), ("artifact files", has_blobs)) if yes
        )
        raise BackupError(
            f"{settings.data_dir}: the target holds {what}; restore into an empty data folder and "
            "database, or pass --force to replace them"
        )

    if kind == "sqlite":
        db_file.parent.mkdir(parents=True, exist_ok=True)
        for suffix in ("-wal", "-shm"):
            Path(f"{db_file}{suffix}").unlink(missing_ok=True)
        _copy_hashed(folder / manifest["database_file"], db_file)
    else:
        conninfo, env = _pg_conninfo(url)
        clean = ["--clean", "--if-exists"] if has_db else []
        _run(
            [
                "pg_restore",
                "--no-owner",
                "--exit-on-error",
                *clean,
                f"--dbname={conninfo}",
                str(folder / manifest["database_file"]),
            ],
            env,
            "pg_restore",
        )

    if force:
        for sub in ("blobs", "tmp"):
            shutil.rmtree(artifact_dir / sub, ignore_errors=True)
    store = ArtifactStore(artifact_dir)
    total = 0
    for sha, size in manifest["artifacts"].items():
        _copy_hashed(folder / "artifacts" / sha[:2] / sha, store.path_of(sha))
        total += size
    if manifest.get("api_key_file"):
        key_file = settings.data_dir / API_KEY_FILE
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        shutil.copy2(folder / API_KEY_FILE, key_file)
        key_file.chmod(0o600)
    return BackupSummary(folder, kind, len(manifest["artifacts"]), total)
