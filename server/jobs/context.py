"""What a running job sees: its parameters, a scratch folder, progress, logging, cancellation.

Cancellation is cooperative: :meth:`JobContext.check` (called by :meth:`progress` and from
the core library's callbacks) raises :class:`JobCancelled` once a cancel was requested, or
:class:`JobInterrupted` when the worker is shutting down or lost the job, so the job stops
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
from server.db.session import session_scope
from server.jobs import queue
from server.services import Services

_PROGRESS_EVERY = 0.5  # seconds between progress writes
_LOG_FLUSH_EVERY = 1.0


class JobCancelled(Exception):
    """The client asked to cancel this job."""


class JobInterrupted(Exception):
    """The worker is stopping or no longer owns the job; it goes back to the queue."""


class JobContext:
    def __init__(self, services: Services, job: Job, worker_id: str, workdir: Path, stopping: threading.Event):
        self.services = services
        self.job_id = job.id
        self.kind = job.kind
        self.params: dict[str, Any] = dict(job.params or {})
        self.worker_id = worker_id
        self.workdir = workdir
        self._stopping = stopping
        self.cancel_requested = threading.Event()
        self.lost = threading.Event()
        self._last_progress = 0.0
        self._pending_logs: list[tuple[str, str]] = []
        self._last_log_flush = 0.0
        self._lock = threading.Lock()
        self.completed_result: dict[str, Any] | None = None

    @property
    def sessions(self):
        return self.services.sessions

    @property
    def store(self):
        return self.services.store

    @property
    def settings(self):
        return self.services.settings

    def session(self):
        """A session that commits on success (``with ctx.session() as s: ...``)."""
        return session_scope(self.services.sessions)

    def check(self) -> None:
        """Raise if the job should stop now."""
        if self.lost.is_set():
            raise JobInterrupted("the worker lost this job's lease")
        if self.cancel_requested.is_set():
            raise JobCancelled("cancelled by request")
        if self._stopping.is_set():
            raise JobInterrupted("worker shutting down")

    def progress(self, fraction: float | None = None, message: str | None = None, force: bool = False) -> None:
        """Report progress in [0, 1] and a short status line (throttled), then :meth:`check`."""
        now = time.monotonic()
        if force or now - self._last_progress >= _PROGRESS_EVERY:
            self._last_progress = now
            try:
                if queue.report_progress(self.sessions, self.job_id, self.worker_id, fraction, message):
                    self.cancel_requested.set()
            except queue.LostJob:
                self.lost.set()
            self.flush_logs()
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
        with self._lock:
            pending, self._pending_logs = self._pending_logs, []
        self._last_log_flush = time.monotonic()
        if not pending:
            return
        with session_scope(self.sessions) as s:
            for level, message in pending:
                queue.append_log(s, self.job_id, message, level)
            queue.trim_log(s, self.job_id, self.settings.job_log_lines)

    def complete(self, register: Callable[[Session], dict[str, Any]]) -> dict[str, Any]:
        """Register the job's outputs and mark it succeeded, in one transaction."""
        self.check()
        self.flush_logs()
        try:
            result = queue.finish(self.sessions, self.job_id, self.worker_id, queue.SUCCEEDED, register=register)
        except queue.LostJob as e:
            self.lost.set()
            raise JobInterrupted(str(e)) from None
        self.completed_result = result or {}
        return self.completed_result


class JobLogHandler(logging.Handler):
    """Copies log records emitted by the job's thread (core library included) into its log."""

    def __init__(self, ctx: JobContext, thread_id: int):
        super().__init__(level=logging.INFO)
        self.ctx = ctx
        self.thread_id = thread_id

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread_id:
            return
        try:
            self.ctx.log(f"{record.name}: {record.getMessage()}", record.levelname)
        except Exception:  # noqa: BLE001 - logging must never break the job
            self.handleError(record)
