"""``csa serve``, ``csa keys``, ``csa doctor``, ``csa backup`` and ``csa restore``: the
service's own commands, added to ``csa`` as plugins.

``csa_core`` never imports the service. Its command line finds this groups through the
``csa.commands`` entry points that ``pyproject.toml`` declares (``register_serve``,
``register_keys``, ``register_doctor``, ``register_backup``, ``register_restore``), so the
dependency runs one way: ``server`` -> ``csa_core``. Jobs run inside the served process or,
with ``CSA_EXECUTOR=ray``, on a Ray cluster that the process dispatches to; there is no
separate worker command (docs/architecture.md, "Executors").

Settings come from CSA_* environment variables (see ``server/settings.py``); flags override
them. The web stack is imported only when a command runs, so building the ``csa`` parser
stays fast and works without the server extra installed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

SERVER_EXTRA_HINT = "the service needs the server extra (pip install 'csa[server]')"


def register_serve(sub: argparse._SubParsersAction) -> None:
    """``csa serve``: the REST API plus its job executor unless ``--no-worker``."""
    p = sub.add_parser("serve", help="run the adaptation service (REST API and its job executor)")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; 0.0.0.0 in containers)",
    )
    p.add_argument("--port", type=int, default=8000)
    p.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="database, artifacts and API key (default: $CSA_DATA_DIR or ./csa-data)",
    )
    p.add_argument(
        "--database-url", default=None, help="SQLAlchemy URL (default: SQLite in the data folder)"
    )
    p.add_argument(
        "--no-worker",
        action="store_true",
        help="run no jobs from this process (an API replica beside one that runs them)",
    )
    p.add_argument(
        "--log-level", default="info", choices=("critical", "error", "warning", "info", "debug")
    )
    p.set_defaults(func=run_serve)


def settings_from_args(args: argparse.Namespace, **overrides: object):
    """Settings from the environment with the command's flags applied."""
    from server.settings import Settings

    values: dict[str, object] = dict(overrides)
    if getattr(args, "data_dir", None) is not None:
        values["data_dir"] = args.data_dir
    if getattr(args, "database_url", None) is not None:
        values["database_url"] = args.database_url
    return Settings(**values)


def run_serve(args: argparse.Namespace) -> int:
    try:
        import uvicorn

        from server.app import create_app
    except ImportError as e:
        print(f"csa serve: {SERVER_EXTRA_HINT}: {e}", file=sys.stderr)
        return 2
    overrides: dict[str, object] = {"embedded_worker": False} if args.no_worker else {}
    app = create_app(settings_from_args(args, **overrides))
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level)
    return 0


def register_keys(sub: argparse._SubParsersAction) -> None:
    """``csa keys create|list|revoke``: the service's API keys, straight in its database
    (docs/operations.md "API keys"); the admin routes under /api/v1/keys do the same."""
    p = sub.add_parser("keys", help="create, list and revoke the service's API keys")
    _data_args(p)
    actions = p.add_subparsers(dest="keys_action", required=True)
    create = actions.add_parser(
        "create", help="make a key and print it once (only its sha256 is stored)"
    )
    create.add_argument(
        "--name", required=True, help="unique name, also after revocation (robot-7)"
    )
    create.add_argument("--scope", required=True, choices=("device", "operator", "admin"))
    create.add_argument(
        "--expires",
        default=None,
        metavar="DURATION",
        help="lifetime: 30d, 12h, 90m or 2w (default: none)",
    )
    listing = actions.add_parser("list", help="the keys: name, prefix, scope, state and times")
    listing.add_argument("--active", action="store_true", help="leave out revoked keys")
    revoke = actions.add_parser(
        "revoke", help="revoke a key by name or prefix (effective at its next request)"
    )
    revoke.add_argument("ref", metavar="NAME|PREFIX")
    p.set_defaults(func=run_keys)


def _when(value) -> str:
    return value.strftime("%Y-%m-%d %H:%M") + "Z" if value is not None else "-"


def run_keys(args: argparse.Namespace) -> int:
    try:
        from server.db.migrate import upgrade_to_head
        from server.db.session import make_engine, make_sessionmaker
        from server.errors import APIError
        from server.keys import key_state
        from server.services.keys import create_key, keys_query, revoke_key
    except ImportError as e:
        print(f"csa keys: {SERVER_EXTRA_HINT}: {e}", file=sys.stderr)
        return 2
    settings = settings_from_args(args)
    engine = make_engine(settings.resolved_database_url)
    try:
        # A fresh data folder gets its tables, as the service would make them.
        upgrade_to_head(engine)
        with make_sessionmaker(engine)() as db:
            if args.keys_action == "create":
                options = {"name": "--name", "scope": "--scope", "expires_in": "--expires"}
                row, key = create_key(db, args.name, args.scope, args.expires, options)
                expiry = f", expires {_when(row.expires_at)}" if row.expires_at else ""
                made = f"created key {row.name!r} (scope {row.scope}{expiry}, prefix {row.prefix})"
                print(f"{made}; store it now, it is not shown again:", file=sys.stderr)
                print(key)
            elif args.keys_action == "list":
                rows = list(db.scalars(keys_query(include_revoked=not args.active)))
                header = (
                    "NAME",
                    "PREFIX",
                    "SCOPE",
                    "STATE",
                    "CREATED",
                    "EXPIRES",
                    "LAST USED",
                    "REVOKED",
                )
                table = [header]
                for k in rows:
                    times = (k.created_at, k.expires_at, k.last_used_at, k.revoked_at)
                    table.append((k.name, k.prefix, k.scope, key_state(k), *map(_when, times)))
                widths = [max(len(r[i]) for r in table) for i in range(len(header))]
                for r in table:
                    print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
            else:
                row = revoke_key(db, args.ref)
                print(f"revoked key {row.name!r} ({row.prefix}) at {_when(row.revoked_at)}")
    except APIError as e:
        print(f"csa keys {args.keys_action}: {e.message}", file=sys.stderr)
        return 1
    finally:
        engine.dispose()
    return 0


def _data_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="the service's data folder (default: $CSA_DATA_DIR or ./csa-data)",
    )
    p.add_argument(
        "--database-url",
        default=None,
        help="the service's database (default: SQLite in the data folder)",
    )


def register_doctor(sub: argparse._SubParsersAction) -> None:
    """``csa doctor``: leftovers of crashes between the database and the artifact store, and
    their repair (docs/operations.md "csa doctor")."""
    p = sub.add_parser(
        "doctor",
        help="find (and repair) orphan blobs, missing blobs, half-written files and stuck jobs",
    )
    _data_args(p)
    p.add_argument(
        "--dry-run", action="store_true", help="only report what is wrong; change nothing"
    )
    p.add_argument(
        "--min-age",
        type=float,
        default=None,
        metavar="SECONDS",
        help=(
            "leave unrecorded files and upload folders younger than this (default: 0 when no "
            "executor is alive, else CSA_ORPHAN_BLOB_GRACE_SECONDS)"
        ),
    )
    p.set_defaults(func=run_doctor)


def run_doctor(args: argparse.Namespace) -> int:
    """Exit 0 when nothing is left wrong, 1 when data is missing or corrupt (a repair cannot
    bring it back) or, with --dry-run, when anything was found."""
    try:
        from sqlalchemy.engine import make_url

        from server.artifacts import ArtifactStore
        from server.db.migrate import upgrade_to_head
        from server.db.session import make_engine, make_sessionmaker
        from server.doctor import examine
    except ImportError as e:
        print(f"csa doctor: {SERVER_EXTRA_HINT}: {e}", file=sys.stderr)
        return 2
    if args.min_age is not None and args.min_age < 0:
        print(f"csa doctor: --min-age must be >= 0, got {args.min_age:g}", file=sys.stderr)
        return 2
    settings = settings_from_args(args)
    url = make_url(settings.resolved_database_url)
    if url.get_backend_name() == "sqlite" and not Path(url.database or "").is_file():
        print(
            f"csa doctor: {url.database}: no database file (wrong --data-dir or --database-url?)",
            file=sys.stderr,
        )
        return 2
    engine = make_engine(settings.resolved_database_url)
    try:
        upgrade_to_head(engine)  # the schema the service's code expects, as csa serve would make it
        report = examine(
            make_sessionmaker(engine),
            ArtifactStore(settings.resolved_artifact_dir),
            settings.resolved_work_dir,
            repair=not args.dry_run,
            min_age_s=args.min_age,
            grace_s=settings.orphan_blob_grace_seconds,
            lease_seconds=settings.lease_seconds,
            max_attempts=settings.max_attempts,
            say=print,
        )
    finally:
        engine.dispose()
    if report.unrepairable:
        print(
            f"csa doctor: {len(report.unrepairable)} stored file(s) missing or corrupt; restore a "
            "backup (docs/operations.md)",
            file=sys.stderr,
        )
        return 1
    if args.dry_run and report.problems:
        return 1
    return 0


def register_backup(sub: argparse._SubParsersAction) -> None:
    """``csa backup DIR``: the database, then the blobs it records, with checksums
    (docs/operations.md "Backup and restore")."""
    p = sub.add_parser(
        "backup", help="copy the service's database and artifact store into a new folder"
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="a new or empty folder")
    _data_args(p)
    p.set_defaults(func=run_backup)


def register_restore(sub: argparse._SubParsersAction) -> None:
    """``csa restore DIR``: a backup in place of the service's data (the service stopped)."""
    p = sub.add_parser(
        "restore", help="put a backup made by csa backup in place of the service's data"
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="a folder made by csa backup")
    _data_args(p)
    p.add_argument(
        "--force",
        action="store_true",
        help="replace a target that already holds a database or artifact files",
    )
    p.set_defaults(func=run_restore)


def run_backup(args: argparse.Namespace) -> int:
    return _backup_or_restore(args, "backup")


def run_restore(args: argparse.Namespace) -> int:
    return _backup_or_restore(args, "restore")


def _backup_or_restore(args: argparse.Namespace, action: str) -> int:
    try:
        from server.backup import BackupError, backup, restore
    except ImportError as e:
        print(f"csa {action}: {SERVER_EXTRA_HINT}: {e}", file=sys.stderr)
        return 2
    settings = settings_from_args(args)
    try:
        if action == "backup":
            done = backup(settings, args.folder)
        else:
            done = restore(settings, args.folder, force=args.force)
    except BackupError as e:
        print(f"csa {action}: {e}", file=sys.stderr)
        return 1
    verb = "backed up" if action == "backup" else "restored"
    print(
        f"{verb} the {done.database} database and {done.artifacts} artifact file(s), "
        f"{done.artifact_bytes} bytes ({done.folder})"
    )
    return 0
