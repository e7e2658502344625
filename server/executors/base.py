"""What every executor does: own jobs in the database and keep that ownership honest.

An executor is the one object in an API process that runs jobs. It registers itself in
``workers``, renews the leases of the jobs it runs from one heartbeat thread (and learns
there which of them were cancelled), recovers jobs whose owner died (``queue.recover_stale_jobs``:
this is what brings jobs back after the API restarts), and removes scratch folders that a
killed process left. Subclasses decide where a claimed job runs: in this process
(:mod:`server.executors.embedded`) or as a Ray task (:mod:`server.executors.ray_cluster`).
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from pathlib import Path

from sqlalchemy import update
from sqlalchemy.orm import Session

from csa_core.errors import CSAInputError
from server.db.models import Job, utcnow
from server.db.models import Worker as WorkerRow
from server.db.session import session_scope
from server.jobs import queue
from server.jobs.context import JobCancelled, JobContext, JobInterrupted, JobLogHandler
from server.services import Services

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted"  # the job stopped without an outcome; it goes back to the queue


def failure(e: Exception) -> tuple[str, str | None]:
    """How an exception ends a job: (status, error), succeeded excepted. Every executor ends a
    job through this, so a job ends the same way wherever it runs (and whichever phase raised)."""
    if isinstance(e, JobCancelled):
        return queue.CANCELLED, "cancelled by request"
    if isinstance(e, JobInterrupted):
        return INTERRUPTED, str(e)
    if isinstance(e, CSAInputError):
        return queue.FAILED, str(e)
    return queue.FAILED, f"{type(e).__name__}: {e}"


def unexpected(e: Exception) -> bool:
    """Whether a failure is a bug or a broken input rather than a cancel, an interruption or a
    user's mistake: its traceback goes into the job's log."""
    return not isinstance(e, JobCancelled | JobInterrupted | CSAInputError)


def run_job_function(ctx: JobContext, run: Callable[[JobContext], None]) -> tuple[str, str | None]:
    """Run a job's phases (``run``) under ``ctx`` with its thread's log records copied into
    the job's log; returns (status, error): succeeded, failed, cancelled or
    :data:`INTERRUPTED`."""
    handler = JobLogHandler(ctx, threading.get_ident())
    logging.getLogger().addHandler(handler)
    try:
        run(ctx)
        return queue.SUCCEEDED, None
    except Exception as e:  # noqa: BLE001 - any failure of the job ends the job, not the executor
        if unexpected(e):
            ctx.log(traceback.format_exc(limit=20), "ERROR")
        return failure(e)
    finally:
        logging.getLogger().removeHandler(handler)


UPLOAD_SCRATCH_AGE_S = 86400.0  # an upload's folder (csa-*) older than this is a killed request's


def stale_scratch(s: Session, work: Path, upload_age_s: float) -> list[Path]:
    """Scratch folders of the work folder that a killed process left: those of jobs no longer
    running (``job-<id>-*``), and upload folders (``csa-*``) last changed more than
    ``upload_age_s`` seconds ago (a younger one may be a request still running)."""
    if not work.is_dir():
        return []
    cutoff = time.time() - upload_age_s
    found: list[Path] = []
    for p in sorted(work.iterdir()):
        parts = p.name.split("-")
        if not p.is_dir():
            continue
        if len(parts) == 3 and parts[0] == "job" and parts[1].isdigit():
            job = s.get(Job, int(parts[1]))
            if job is None or job.status != queue.RUNNING:
                found.append(p)
        elif parts[0] == "csa" and p.stat().st_mtime < cutoff:
            found.append(p)
    return found


class Executor:
    """Base of the executors: registration, heartbeat and lease renewal, recovery, the loop."""

    mode = "embedded"

    def __init__(self, services: Services):
        self.services = services
        self.settings = services.settings
        self.id = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._beat_stop = threading.Event()
        self._beater: threading.Thread | None = None

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Run in a daemon thread of the API process."""
        self._thread = threading.Thread(
            target=self.run_forever, name=f"csa-{self.mode}-{self.id}", daemon=True
        )
        self._thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        self.stopping.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def run_forever(self) -> None:
        self._register()
        self._beat_stop.clear()
        self._beater = threading.Thread(
            target=self._heartbeat_loop, name=f"csa-heartbeat-{self.id}", daemon=True
        )
        self._beater.start()
        try:
            self.open()
            while not self.stopping.is_set():
                try:
                    ran = self.step()
                except Exception:  # noqa: BLE001 - a database hiccup must not kill the executor
                    log.exception("executor loop error")
                    ran = False
                if not ran:
                    self.stopping.wait(self.settings.worker_poll_seconds)
        finally:
            try:
                self.close()
            except Exception:  # noqa: BLE001
                log.exception("executor %s did not close cleanly", self.id)
            self._beat_stop.set()
            self._beater.join(10)
            self._unregister()

    # -- what a subclass provides --------------------------------------------------------

    def open(self) -> None:
        """Called in the executor's thread before the first :meth:`step`."""

    def step(self) -> bool:
        """One round of work; returns whether anything ran (else the loop waits a poll)."""
        raise NotImplementedError

    def close(self) -> None:
        """Called in the executor's thread when it stops: hand running jobs back."""

    def on_leases(self, owned: set[int], cancel: set[int], since: float) -> None:
        """From the heartbeat thread: the jobs this executor still owns, and which of them
        were cancelled by a client, as the database said after ``since`` (``time.monotonic()``
        before the renewal began). A job claimed after ``since`` may be missing from ``owned``
        without being lost: the next beat tells."""

    # -- registration, heartbeat, recovery -----------------------------------------------

    def _register(self) -> None:
        queue.note_local_owner(self.id, True)
        with session_scope(self.services.sessions) as s:
            s.add(
                WorkerRow(
                    id=self.id, hostname=socket.gethostname(), pid=os.getpid(), mode=self.mode
                )
            )
        self.recover()  # jobs of a process that died (this API before a restart) go back first
        self._remove_stale_scratch()
        log.info("executor %s started (%s)", self.id, self.mode)

    def _unregister(self) -> None:
        queue.note_local_owner(self.id, False)
        try:
            with session_scope(self.services.sessions) as s:
                s.execute(
                    update(WorkerRow)
                    .where(WorkerRow.id == self.id)
                    .values(stopped_at=utcnow(), current_job_id=None)
                )
        except Exception:  # noqa: BLE001
            log.exception("could not mark executor %s stopped", self.id)
        log.info("executor %s stopped", self.id)

    def _beat(self, job_id: int | None = None) -> None:
        with session_scope(self.services.sessions) as s:
            s.execute(
                update(WorkerRow)
                .where(WorkerRow.id == self.id)
                .values(heartbeat_at=utcnow(), current_job_id=job_id)
            )

    def current_job(self) -> int | None:
        return None

    def _heartbeat_loop(self) -> None:
        while not self._beat_stop.wait(self.settings.heartbeat_seconds):
            try:
                since = time.monotonic()
                owned, cancel = queue.renew_leases(
                    self.services.sessions, self.id, self.settings.lease_seconds
                )
                self._beat(self.current_job())
                self.on_leases(owned, cancel, since)
            except Exception:  # noqa: BLE001 - try again at the next beat
                log.exception("heartbeat of executor %s failed", self.id)

    def recover(self) -> None:
        for job_id in queue.recover_stale_jobs(self.services.sessions, self.settings.max_attempts):
            log.warning("recovered job %s from a lost owner", job_id)

    def _remove_stale_scratch(self) -> None:
        """Delete scratch folders left by a killed process (:func:`stale_scratch`)."""
        with session_scope(self.services.sessions) as s:
            for p in stale_scratch(s, self.settings.resolved_work_dir, UPLOAD_SCRATCH_AGE_S):
                shutil.rmtree(p, ignore_errors=True)

    def scratch_folder(self, job_id: int) -> str:
        """A new folder name under the work dir for a job (``job-<id>-<random>``)."""
        return f"job-{job_id}-{uuid.uuid4().hex[:6]}"

    def end(self, job_id: int, status: str, error: str | None) -> None:
        """End a job this executor owns with ``status`` (failed or cancelled)."""
        try:
            queue.finish(self.services.sessions, job_id, self.id, status, error=error)
        except queue.LostJob:
            log.warning("job %s was recovered by another executor before it ended", job_id)
        log.info("job %s %s: %s", job_id, status, error)
