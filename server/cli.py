"""``csa serve``: the service's own command, added to ``csa`` as a plugin.

``csa_core`` never imports the service. Its command line finds this group through the
``csa.commands`` entry point that ``pyproject.toml`` declares (``register_serve``), so the
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
