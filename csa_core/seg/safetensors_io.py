"""Reading safetensors files without unpickling anything: every tensor, or the header alone
(dtypes and shapes), with the file's string metadata. Errors name the file.

Shared by the checkpoints (:mod:`csa_core.seg.checkpoint`) and the import of foreign
weights (:func:`csa_core.seg.models.load_foreign_weights`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from safetensors import SafetensorError, safe_open
from torch import Tensor

from csa_core.errors import CSAInputError

T = TypeVar("T")


def _read_safetensors(path: str | Path, read: Callable[[Any], T]) -> tuple[T, dict[str, str]]:
    """``read(f)`` of the open safetensors file ``f`` and the file's string metadata; a missing
    or unreadable file raises :class:`CSAInputError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise CSAInputError(path, "checkpoint file not found")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            return read(f), dict(f.metadata() or {})
    except (SafetensorError, OSError, RuntimeError, ValueError) as e:
        raise CSAInputError(path, f"not a readable safetensors file ({e})") from None


def read_safetensors(path: str | Path) -> tuple[dict[str, Tensor], dict[str, str]]:
    """All tensors (on CPU) and the string metadata of a safetensors file; errors name the file."""
    return _read_safetensors(path, lambda f: {name: f.get_tensor(name) for name in f.keys()})


def _layout(f: Any) -> dict[str, tuple[str, tuple[int, ...]]]:
    views = {name: f.get_slice(name) for name in f.keys()}
    return {
        name: (str(v.get_dtype()), tuple(int(n) for n in v.get_shape()))
        for name, v in views.items()
    }


def read_safetensors_header(
    path: str | Path,
) -> tuple[dict[str, tuple[str, tuple[int, ...]]], dict[str, str]]:
    """Each tensor's (safetensors dtype such as ``F32``, shape) and the string metadata of a
    safetensors file, from its header alone: no tensor is read."""
    return _read_safetensors(path, _layout)
