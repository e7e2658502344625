"""Errors that the CLI and the server turn into one-line messages instead of tracebacks."""

from __future__ import annotations

from numbers import Integral
from pathlib import Path


class CSAInputError(ValueError):
    """Bad user input: names the offending file or field and says what is wrong."""

    def __init__(self, where: str | Path, problem: str):
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")


def check_seed(seed: object, field: str = "--seed") -> int:
    """``seed`` as an int when it is a non-negative integer (numpy integers too, not bools),
    else a :class:`CSAInputError` naming ``field``: the one seed check of the data generators."""
    if isinstance(seed, bool) or not isinstance(seed, Integral) or seed < 0:
        raise CSAInputError(field, f"must be a non-negative integer, got {seed!r}")
    return int(seed)
