"""``csa serve`` and ``csa keys``: the service's own commands, added to ``csa`` as plugins.

``csa_core`` never imports the service. Its command line finds this groups through the
``csa.commands`` entry points that ``pyproject.toml`` declares (``register_serve``,
``register_keys``), so the
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
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; 0.0.0.0 in containers)")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--data-dir", type=Path, default=None, help="database, artifacts and API key (default: $CSA_DATA_DIR or ./csa-data)")
    p.add_argument("--database-url", default=None, help="SQLAlchemy URL (default: SQLite in the data folder)")
    p.add_argument("--no-worker", action="store_true", help="run no jobs from this process (an API replica beside one that runs them)")
    p.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
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
    p.add_argument("--data-dir", type=Path, default=None, help="the service's data folder (default: $CSA_DATA_DIR or ./csa-data)")
    p.add_argument("--database-url", default=None, help="the service's database (default: SQLite in the data folder)")
    actions = p.add_subparsers(dest="keys_action", required=True)
    create = actions.add_parser("create", help="make a key and print it once (only its sha256 is stored)")
    create.add_argument("--name", required=True, help="unique name, also after revocation (robot-7)")
    create.add_argument("--scope", required=True, choices=("device", "operator", "admin"))
    create.add_argument("--expires", default=None, metavar="DURATION", help="lifetime: 30d, 12h, 90m or 2w (default: none)")
    listing = actions.add_parser("list", help="the keys: name, prefix, scope, state and times")
    listing.add_argument("--active", action="store_true", help="leave out revoked keys")
    revoke = actions.add_parser("revoke", help="revoke a key by name or prefix (effective at its next request)")
    revoke.add_argument("ref", metavar="NAME|PREFIX")
    p.set_defaults(func=run_keys)


def _when(value) -> str:
    return value.strftime("%Y-%m-%d %H:%M") + "Z" if value is not None else "-"


def run_keys(args: argparse.Namespace) -> int:
    try:
        from server.db.migrate import upgrade_to_head
        from server.db.session import make_engine, make_sessionmaker
        from server.errors import APIError
        from server.keys import create_key, key_state, keys_query, revoke_key
    except ImportError as e:
        print(f"csa keys: {SERVER_EXTRA_HINT}: {e}", file=sys.stderr)
        return 2
    settings = settings_from_args(args)
    engine = make_engine(settings.resolved_database_url)
    try:
        upgrade_to_head(engine)  # a fresh data folder gets its tables, as the service would make them
        with make_sessionmaker(engine)() as db:
            if args.keys_action == "create":
                row, key = create_key(db, args.name, args.scope, args.expires)
                expiry = f", expires {_when(row.expires_at)}" if row.expires_at else ""
                print(f"created key {row.name!r} (scope {row.scope}{expiry}, prefix {row.prefix}); store it now, it is not shown again:", file=sys.stderr)
                print(key)
            elif args.keys_action == "list":
                rows = list(db.scalars(keys_query(include_revoked=not args.active)))
                header = ("NAME", "PREFIX", "SCOPE", "STATE", "CREATED", "EXPIRES", "LAST USED", "REVOKED")
                table = [header] + [
                    (k.name, k.prefix, k.scope, key_state(k), _when(k.created_at), _when(k.expires_at), _when(k.last_used_at), _when(k.revoked_at))
                    for k in rows
                ]
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
