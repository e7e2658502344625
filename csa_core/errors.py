"""Errors that the CLI and the server turn into one-line messages instead of tracebacks."""

from __future__ import annotations

from pathlib import Path


class CSAInputError(ValueError):
    """Bad user input: names the offending file or field and says what is wrong."""

    def __init__(self, where: str | Path, problem: str):
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")
