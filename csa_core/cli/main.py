"""Entry point of ``csa``: local data, NeRF, segmentation, adaptation, experiments and demo.

Other packages add command groups through the ``csa.commands`` entry points (the service adds
``serve`` this way, see ``server/cli.py``), so ``csa_core`` never imports them.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from importlib.metadata import entry_points

from csa_core import __version__
from csa_core.errors import CSAInputError

# Command groups in data-flow order; each module exposes register(subparsers).
GROUPS = ("data", "nerf", "seg", "adapt", "experiment", "eval", "demo")
# Entry-point group through which installed packages add commands: each entry point names a
# callable register(subparsers) that adds one sub-command (and imports nothing heavy).
PLUGIN_GROUP = "csa.commands"


def register_plugins(sub: argparse._SubParsersAction) -> None:
    """Add the command groups other installed packages declare under ``csa.commands``.

    A plugin that cannot be imported (its package is missing) is left out with a one-line
    note on stderr, so ``csa`` keeps working for everything else."""
    added: dict[str, str] = {}
    for ep in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name):
        if added.get(ep.name) == ep.value:
            continue  # the same plugin seen twice (e.g. two copies of the metadata on the path)
        if ep.name in sub.choices:
            print(
                f"csa: note: command {ep.name!r} from {ep.value} ignored: the name is taken",
                file=sys.stderr,
            )
            continue
        try:
            register = ep.load()
        except ImportError as e:
            print(f"csa: note: command {ep.name!r} unavailable ({ep.value}): {e}", file=sys.stderr)
            continue
        register(sub)
        added[ep.name] = ep.value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="csa", description="Continual semantic adaptation through neural rendering."
    )
    parser.add_argument("--version", action="version", version=f"csa {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging and full tracebacks"
    )
    sub = parser.add_subparsers(dest="group", metavar="COMMAND", required=True)
    for name in GROUPS:
        importlib.import_module(f"csa_core.cli.{name}").register(sub)
    register_plugins(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
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
