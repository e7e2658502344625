"""Argument types shared by the command groups; bad values name the flag that carried them."""

from __future__ import annotations

import argparse


def size_arg(text: str) -> tuple[int, int]:
    """argparse type for ``WxH`` -> (width, height) (:func:`csa_core.data.camera.parse_size`)."""
    from csa_core.data.camera import parse_size
    from csa_core.errors import CSAInputError

    try:
        return parse_size(text)
    except CSAInputError as err:
        raise argparse.ArgumentTypeError(err.problem) from None


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def add_set_argument(parser: argparse.ArgumentParser, config: str, example: str) -> None:
    """The repeatable ``--set KEY=VALUE`` flag: a field of the command's ``config`` (the name of
    its dataclass), applied after the preset and the dedicated flags (``csa_core.overrides``)."""
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"set a field of the {config} after the preset and the other flags, e.g. "
        f'{example}; repeatable (docs/presets.md "Overriding a preset")',
    )
