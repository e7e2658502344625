"""Fault points: a test-only hook that makes the process die (or its disk look full) at a
named place in a write path, so that tests can show what a crash there leaves behind.

**For tests only.** Production code calls :func:`point` at the places listed in
:data:`POINTS`; it does nothing unless the environment variable ``CSA_FAULT_POINT`` names that
point when the process starts (docs/operations.md "Fault points (tests only)")::

    CSA_FAULT_POINT=NAME[:COUNT[:ACTION]]

``COUNT`` (default 1) is the hit of the point that fires: ``frame.blobs_written:2`` lets the
first frame through and fires at the second. ``ACTION`` is ``kill`` (default:
``os.kill(os.getpid(), SIGKILL)``, a crash that runs no ``finally`` block, no atexit hook and
no database rollback) or ``enospc`` (raise ``OSError(ENOSPC)`` at that hit and every later
one, as a full disk would).

The variable is read once, when this module is first imported; :func:`configure` replaces
the setting for tests that run the service in their own process.
"""

from __future__ import annotations

import errno
import os
import signal
import threading
from dataclasses import dataclass

ENV = "CSA_FAULT_POINT"

# Every point production code calls, with where it sits. A name not listed here is refused
# when the variable is read, so a misspelt point cannot silently never fire.
POINTS: dict[str, str] = {
    "artifact.write": (
        "the artifact store is about to write a blob's temporary file (server/artifacts.py)"
    ),
    "artifact.tmp_written": (
        "a blob's temporary file is written, not yet renamed to its checksum name"
    ),
    "artifact.file_stored": (
        "a file (checkpoint, model) is in the store under its checksum, its row not yet committed"
    ),
    "frame.blobs_written": (
        "a frame's images are in the store, its row not yet committed (server/frame_store.py)"
    ),
    "archive.extracted": "an uploaded archive is extracted in the work folder, no frame stored yet",
    "archive.frame_stored": (
        "one frame of an archive is stored in the open transaction, the archive not yet committed"
    ),
    "job.computed": (
        "a job's computation is done, its outputs not yet registered (server/jobs/phases.py)"
    ),
    "job.registering": (
        "a job's outputs are written and flushed, the transaction that ends the job not yet "
        "committed"
    ),
}
ACTIONS = ("kill", "enospc")


@dataclass(frozen=True)
class Fault:
    name: str
    count: int = 1
    action: str = "kill"


def parse(value: str | None) -> Fault | None:
    """The fault a ``CSA_FAULT_POINT`` value asks for (None when empty); ValueError naming
    the variable and what is wrong otherwise."""
    if value is None or not value.strip():
        return None
    parts = value.strip().split(":")
    if len(parts) > 3:
        raise ValueError(f"{ENV}={value!r}: expected NAME[:COUNT[:ACTION]]")
    name = parts[0]
    if name not in POINTS:
        raise ValueError(f"{ENV}={value!r}: unknown point {name!r} (known: {', '.join(POINTS)})")
    count = 1
    if len(parts) > 1:
        if not parts[1].isdigit() or int(parts[1]) < 1:
            raise ValueError(
                f"{ENV}={value!r}: COUNT must be a whole number >= 1, got {parts[1]!r}"
            )
        count = int(parts[1])
    action = parts[2] if len(parts) > 2 else "kill"
    if action not in ACTIONS:
        raise ValueError(
            f"{ENV}={value!r}: ACTION must be one of {', '.join(ACTIONS)}, got {action!r}"
        )
    return Fault(name, count, action)


_lock = threading.Lock()
_fault: Fault | None = None
_hits = 0


def configure(value: str | None) -> Fault | None:
    """Arm the fault that ``value`` names (``None`` or empty: none) and reset its hit count."""
    global _fault, _hits
    fault = parse(value)
    with _lock:
        _fault, _hits = fault, 0
    return fault


def active() -> Fault | None:
    return _fault


def point(name: str) -> None:
    """A named place in a write path: nothing happens unless ``CSA_FAULT_POINT`` names it."""
    fault = _fault
    if fault is None or fault.name != name:
        return
    if name not in POINTS:  # pragma: no cover - a call site with a name missing from POINTS
        raise ValueError(f"fault point {name!r} is not in server.faults.POINTS")
    global _hits
    with _lock:
        _hits += 1
        hit = _hits
    if hit < fault.count:
        return
    if fault.action == "enospc":
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    if hit == fault.count:
        os.kill(os.getpid(), signal.SIGKILL)


configure(os.environ.get(ENV))
