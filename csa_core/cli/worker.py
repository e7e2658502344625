"""``csa worker``: run queued jobs from the service database in this process.

Any number of workers (and servers with embedded workers) can share one database; jobs of
one model lineage still run one after another. SIGINT/SIGTERM hand the running job back to
the queue.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="run jobs of the adaptation service (standalone worker)")
    p.add_argument("--data-dir", type=Path, default=None, help="same data folder as the server (default: $CSA_DATA_DIR or ./csa-data)")
    p.add_argument("--database-url", default=None, help="same database as the server (default: SQLite in the data folder)")
    p.set_defaults(func=run_worker)


def run_worker(args: argparse.Namespace) -> int:
    try:
        from csa_core.cli.serve import settings_from_args
        from server.services import open_services
        from server.worker import run_standalone
    except ImportError as e:
        print(f"csa worker: the service needs the server extra (pip install 'csa[server]'): {e}", file=sys.stderr)
        return 2
    services = open_services(settings_from_args(args))
    try:
        return run_standalone(services)
    finally:
        services.close()
