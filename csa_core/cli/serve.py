"""``csa serve``: run the HTTP service (API plus an embedded worker unless --no-worker).

Settings come from CSA_* environment variables (see server/settings.py); flags override them.
The web stack is imported only when the command runs, so ``csa_core`` needs no web packages.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the adaptation service (REST API and job worker)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; 0.0.0.0 in containers)")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--data-dir", type=Path, default=None, help="database, artifacts and API key (default: $CSA_DATA_DIR or ./csa-data)")
    p.add_argument("--database-url", default=None, help="SQLAlchemy URL (default: SQLite in the data folder)")
    p.add_argument("--no-worker", action="store_true", help="do not run jobs in this process (use `csa worker`)")
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
        print(f"csa serve: the service needs the server extra (pip install 'csa[server]'): {e}", file=sys.stderr)
        return 2
    overrides: dict[str, object] = {"embedded_worker": False} if args.no_worker else {}
    app = create_app(settings_from_args(args, **overrides))
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level)
    return 0
