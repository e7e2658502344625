"""The three phases of a job, and the plain values that travel between them.

Every job kind (``server/jobs/kinds.py``) is three functions, and both executors run the same
three (``server/executors``):

- ``gather(session, params, node) -> Inputs``, on the API node: reads the database and names
  the artifact store's files the job needs (:class:`FileRef`: a path and its checksum);
- ``compute(inputs, workdir, ctx) -> Outputs``: core library calls and files only, no
  database; ``ctx`` (:class:`server.jobs.context.JobContext`) reports progress and log lines,
  checks for a cancel and says which device to use. Files it makes go under ``workdir``;
- ``register(session, outputs, node) -> result``, on the API node: writes the outputs (model
  versions, NeRF checkpoints, scores) in the transaction that marks the job succeeded.

Inputs and Outputs are plain dataclasses: their fields hold None, booleans, numbers, strings,
paths, lists and tuples, dictionaries with string keys, and other such dataclasses
(:func:`check_plain`), so the Ray executor can send them to a worker and back as values,
with the files they name, and nothing else crosses between the API node and a worker.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from server import faults
from server.artifacts import ArtifactMissing, ArtifactStore

if TYPE_CHECKING:
    from server.jobs.context import JobContext

# gather(session, params, node) -> Inputs; compute(inputs, workdir, ctx) -> Outputs;
# register(session, outputs, node) -> the job's result
Gather = Callable[[Session, dict[str, Any], "ApiNode"], Any]
Compute = Callable[[Any, Path, "JobContext"], Any]
Register = Callable[[Session, Any, "ApiNode"], dict[str, Any]]


@dataclass(frozen=True)
class ApiNode:
    """What ``gather`` and ``register`` see besides their session: the job and the API
    node's artifact store."""

    job_id: int
    store: ArtifactStore


@dataclass(frozen=True)
class FileRef:
    """A file a job reads: where it is and its checksum. ``gather`` names the artifact
    store's blob (:func:`stored_file`); the Ray executor ships it and points ``path`` at the
    worker's copy."""

    path: Path
    sha256: str


def stored_file(store: ArtifactStore, sha256: str) -> FileRef:
    """The artifact store's file with checksum ``sha256`` (checked when it is read)."""
    return FileRef(store.path_of(sha256), sha256)


def existing(ref: FileRef) -> Path:
    """The path of ``ref``; :class:`ArtifactMissing` when there is no file."""
    if not Path(ref.path).is_file():
        raise ArtifactMissing(f"artifact {ref.sha256[:12]} is missing from the store")
    return Path(ref.path)


def link(ref: FileRef, dest: Path) -> Path:
    """Make ``dest`` a copy of ``ref`` (a hard link when possible: inputs are never modified)."""
    src = existing(ref)
    dest.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dest)
    except OSError:
        shutil.copyfile(src, dest)
    return dest


# -- plain values --------------------------------------------------------------------------

_LEAVES = (type(None), bool, int, float, str, PurePath)


def check_plain(value: Any, where: str = "value") -> None:
    """Raise TypeError naming the field when ``value`` holds anything but None, booleans,
    numbers, strings, paths, lists, tuples, dictionaries with string keys and dataclasses of
    such values."""
    if isinstance(value, _LEAVES):
        return
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            check_plain(getattr(value, f.name), f"{where}.{f.name}")
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            check_plain(item, f"{where}[{i}]")
    elif isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"{where}: key {key!r} is a {type(key).__name__}, not a string")
            check_plain(item, f"{where}[{key!r}]")
    else:
        raise TypeError(f"{where}: a {type(value).__name__} is not a plain value")


def leaves(value: Any, kind: type | tuple[type, ...]) -> Iterator[Any]:
    """Every value of type ``kind`` inside ``value`` (a plain value), depth first."""
    if isinstance(value, kind):
        yield value
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            yield from leaves(getattr(value, f.name), kind)
    elif isinstance(value, list | tuple):
        for item in value:
            yield from leaves(item, kind)
    elif isinstance(value, dict):
        for item in value.values():
            yield from leaves(item, kind)


def replace_leaves(value: Any, kind: type | tuple[type, ...], change: Callable[[Any], Any]) -> Any:
    """A copy of ``value`` (a plain value) with every value of type ``kind`` replaced by
    ``change(it)``."""
    if isinstance(value, kind):
        return change(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {
            f.name: replace_leaves(getattr(value, f.name), kind, change)
            for f in dataclasses.fields(value)
            if f.init
        }
        return dataclasses.replace(value, **fields)
    if isinstance(value, list | tuple):
        return type(value)(replace_leaves(item, kind, change) for item in value)
    if isinstance(value, dict):
        return {key: replace_leaves(item, kind, change) for key, item in value.items()}
    return value


# -- running the phases ----------------------------------------------------------------------


def gather_inputs(gather: Gather, session: Session, params: dict[str, Any], node: ApiNode) -> Any:
    """Run ``gather`` and check that its Inputs are plain values."""
    inputs = gather(session, params, node)
    check_plain(inputs, "inputs")
    return inputs


def compute_outputs(compute: Compute, inputs: Any, workdir: Path, ctx: JobContext) -> Any:
    """Run ``compute``, check that its Outputs are plain values whose paths name files it made
    in ``workdir`` (what the Ray executor sends back) and that the job may still end (not
    cancelled, not lost), and deliver its last log lines before it is registered."""
    outputs = compute(inputs, workdir, ctx)
    check_plain(outputs, "outputs")
    root = workdir.resolve()
    for path in leaves(outputs, PurePath):
        if not Path(path).is_file() or not Path(path).resolve().is_relative_to(root):
            raise ValueError(
                f"the outputs name {str(path)!r}, which is not a file the job made in its folder"
            )
    ctx.check()
    ctx.flush_logs()
    faults.point("job.computed")
    return outputs


def function_path(function: Callable[..., Any]) -> str:
    """``module:name`` of a module-level function, the way a Ray task names the ``compute``
    it runs (the function travels by name, never as pickled code)."""
    name = getattr(function, "__qualname__", "")
    if not name or "<" in name or "." in name:
        raise ValueError(
            f"{function!r} is not a module-level function; a job's compute must be one"
        )
    return f"{function.__module__}:{name}"


def resolve_function(path: str) -> Callable[..., Any]:
    """The function a :func:`function_path` names."""
    module, _, name = path.partition(":")
    function = getattr(importlib.import_module(module), name)
    if not callable(function):
        raise TypeError(f"{path} is not a function")
    return function
