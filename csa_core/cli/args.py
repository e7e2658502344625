"""Argument types shared by the command groups; bad values name the flag that carried them."""

from __future__ import annotations

import argparse


def size_arg(text: str) -> tuple[int, int]:
    """Parse ``WxH`` into (width, height)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH (e.g. 160x120), got {text!r}") from None
    if w < 8 or h < 8 or w > 8192 or h > 8192:
        raise argparse.ArgumentTypeError(f"width and height must be within 8..8192, got {text!r}")
    return w, h


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v
