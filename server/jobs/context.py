"""What a job's ``compute`` phase sees: progress, logging, cancellation and its settings.

``compute(inputs, workdir, ctx)`` (``server/jobs/phases.py``) gets a :class:`JobContext`:
``ctx.progress`` / ``ctx.core_progress`` / ``ctx.log``, ``ctx.check()`` and ``ctx.settings``
(the device and thread count); it has no database session and no artifact store.
:class:`LocalJobContext` reports to this process's database (the embedded executor);
``server.executors.remote.RemoteJobContext`` reports from inside a Ray task through a channel
actor on the API node.

Cancellation is cooperative: :meth:`JobContext.check` (called by :meth:`progress` and from
the core library's callbacks) raises :class:`JobCancelled` once a cancel was requested, or
:class:`JobInterrupted` when the executor is shutting down or lost the job, so the job stops
between steps and nothing half-made is registered.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from server.db.models import Job
from server.jobs import queue
from server.services import Services

_PROGRESS_EVERY = 0.5  # seconds between progress reports
_LOG_FLUSH_EVERY = 1.0


class JobCancelled(Exception):
    """The client asked to cancel this job."""


class JobInterrupted(Exception):
    """The executor is stopping or no longer owns the job; it goes back to the queue."""


class JobContext:
    """The part every executor shares: throttled progress, buffered logs, cancellation.
    Subclasses implement :meth:`_send` (where progress and logs go, and whether a cancel was
    asked) and :attr:`settings`."""

    def __init__(
        self, job_id: int, kind: str, workdir: Path, stopping: threading.Event | None = None
    ):
        self.job_id = job_id
        self.kind = kind
        self.workdir = workdir
        self._stopping = stopping or threading.Event()
        self.cancel_requested = threading.Event()
        self.lost = threading.Event()
        self._last_progress = 0.0
        self._pending_logs: list[tuple[str, str]] = []
        self._last_log_flush = 0.0
        self._lock = threading.Lock()

    # -- what each executor provides -----------------------------------------------------

    @property
    def settings(self) -> Any:
        """What a job reads of the settings: ``device``, ``torch_threads``."""
        raise NotImplementedError

    def _send(
        self, progress: float | None, message: str | None, logs: list[tuple[str, str]]
    ) -> None:
        """Deliver progress and log lines; set :attr:`cancel_requested` / :attr:`lost`."""
        raise NotImplementedError

    # -- what a job calls ----------------------------------------------------------------

    def check(self) -> None:
        """Raise if the job should stop now."""
        if self.lost.is_set():
            raise JobInterrupted("the executor lost this job")
        if self.cancel_requested.is_set():
            raise JobCancelled("cancelled by request")
        if self._stopping.is_set():
            raise JobInterrupted("executor shutting down")

    def progress(
        self, fraction: float | None = None, message: str | None = None, force: bool = False
    ) -> None:
        """Report progress in [0, 1] and a short status line (throttled), then :meth:`check`."""
        now = time.monotonic()
        if force or now - self._last_progress >= _PROGRESS_EVERY:
            self._last_progress = now
            self._flush(fraction, message)
        self.check()

    def core_progress(self, start: float, end: float) -> Callable[[str, float], None]:
        """The core library's ``on_progress`` for the phase [start, end] of this job: it reports
        the core's message and fraction, then checks, so a cancel stops a long core loop within
        an epoch, a joint round or ten NeRF steps instead of at the end of the phase."""

        def on_progress(message: str, fraction: float) -> None:
            self.progress(start + (end - start) * fraction, message)

        return on_progress

    def log(self, message: str, level: str = "INFO") -> None:
        with self._lock:
            self._pending_logs.append((level, message))
        if time.monotonic() - self._last_log_flush >= _LOG_FLUSH_EVERY:
            self.flush_logs()

    def flush_logs(self) -> None:
        self._flush(None, None)

    def _flush(self, progress: float | None, message: str | None) -> None:
        with self._lock:
            pending, self._pending_logs = self._pending_logs, []
        self._last_log_flush = time.monotonic()
        if pending or progress is not None or message is not None:
            self._send(progress, message, pending)


class LocalJobContext(JobContext):
    """A job run by the embedded executor: progress and log lines go straight to this
    process's database, and :meth:`finish` registers the outputs there."""

    def __init__(
        self, services: Services, job: Job, owner: str, workdir: Path, stopping: threading.Event
    ):
        super().__init__(job.id, job.kind, workdir, stopping)
        self.services = services
        self.owner = owner

    @property
    def settings(self):
        return self.services.settings

    def _send(
        self, progress: float | None, message: str | None, logs: list[tuple[str, str]]
    ) -> None:
        try:
            if queue.report(
                self.services.sessions,
                self.job_id,
                self.owner,
                progress,
                message,
                logs,
                self.settings.job_log_lines,
            ):
                self.cancel_requested.set()
        except queue.LostJob:
            self.lost.set()

    def finish(self, register: Callable[[Session], dict[str, Any]]) -> dict[str, Any]:
        """Run ``register`` in the transaction that marks the job succeeded
        (``queue.finish``); :class:`JobInterrupted` when this executor lost the job."""
        try:
            result = queue.finish(
                self.services.sessions, self.job_id, self.owner, queue.SUCCEEDED, register=register
            )
        except queue.LostJob as e:
            self.lost.set()
            raise JobInterrupted(str(e)) from None
        return result or {}


class JobLogHandler(logging.Handler):
    """Copies log records emitted by the job's thread (core library included) into its log."""

    def __init__(self, ctx: JobContext, thread_id: int):
        super().__init__(level=logging.INFO)
        self.ctx = ctx
        self.thread_id = thread_id
        self._emitting = False  # a record logged while delivering the log is not copied again

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread_id or self._emitting:
            return
        self._emitting = True
        try:
            self.ctx.log(f"{record.name}: {record.getMessage()}", record.levelname)
        except Exception:  # noqa: BLE001 - logging must never break the job
            self.handleError(record)
        finally:
            self._emitting = False
