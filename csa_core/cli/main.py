"""Entry point of ``csa``: local data, NeRF, segmentation, adaptation, experiments and serving."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from csa_core import __version__
from csa_core.errors import CSAInputError

# Command groups in data-flow order; each module exposes register(subparsers).
GROUPS = ("data", "nerf", "seg", "adapt", "experiment", "eval", "demo", "serve", "worker")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="csa", description="Continual semantic adaptation through neural rendering.")
    parser.add_argument("--version", action="version", version=f"csa {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging and full tracebacks")
    sub = parser.add_subparsers(dest="group", metavar="COMMAND", required=True)
    for name in GROUPS:
        importlib.import_module(f"csa_core.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except CSAInputError as e:
        if args.verbose:
            raise
        print(f"csa: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if args.verbose:
            raise
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"csa: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("csa: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
