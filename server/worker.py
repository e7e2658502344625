"""The job worker: claims queued jobs from the database and runs them one at a time.

Embedded by default (a thread started with the API) and also standalone (``csa worker``);
any number of workers can share one database. A worker

- registers itself in ``workers`` and refreshes its heartbeat;
- claims the oldest runnable job (jobs of one model lineage run one after another);
- keeps a lease on the running job from a heartbeat thread; a job whose lease expires, or
  whose worker process is gone from this host, is re-queued by the next worker that looks
  (or failed with the reason once it has been lost ``max_attempts`` times);
- stops a job when it is cancelled (at the job's next check) and, on shutdown, hands its
  running job back to the queue without counting the attempt.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import threading
import time
import traceback
import uuid

from sqlalchemy import update

from csa_core.errors import CSAInputError
from server.db.models import Job, utcnow
from server.db.models import Worker as WorkerRow
from server.db.session import session_scope
from server.jobs import queue
from server.jobs.context import JobCancelled, JobContext, JobInterrupted, JobLogHandler
from server.jobs.kinds import KINDS, runnable_kinds
from server.services import Services

log = logging.getLogger(__name__)


class Worker:
    def __init__(self, services: Services, mode: str = "embedded"):
        self.services = services
        self.settings = services.settings
        self.mode = mode
        self.id = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self.current_job: int | None = None

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Run in a daemon thread (the embedded worker)."""
        self._thread = threading.Thread(target=self.run_forever, name=f"csa-worker-{self.id}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        self.stopping.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def run_forever(self) -> None:
        self._register()
        try:
            while not self.stopping.is_set():
                try:
                    ran = self.run_once()
                except Exception:  # noqa: BLE001 - a database hiccup must not kill the worker
                    log.exception("worker loop error")
                    ran = False
                if not ran:
                    self.stopping.wait(self.settings.worker_poll_seconds)
        finally:
            self._unregister()

    def _register(self) -> None:
        queue.note_local_worker(self.id, True)
        with session_scope(self.services.sessions) as s:
            s.add(WorkerRow(id=self.id, hostname=socket.gethostname(), pid=os.getpid(), mode=self.mode))
        if self.settings.torch_threads:
            import torch

            torch.set_num_threads(self.settings.torch_threads)
        self._remove_stale_scratch()
        log.info("worker %s started (%s)", self.id, self.mode)

    def _remove_stale_scratch(self) -> None:
        """Delete scratch folders left by a killed process: those of jobs no longer running,
        and upload folders (``csa-*``) older than a day."""
        work = self.settings.resolved_work_dir
        if not work.is_dir():
            return
        day_ago = time.time() - 86400
        with session_scope(self.services.sessions) as s:
            for p in work.iterdir():
                parts = p.name.split("-")
                if not p.is_dir():
                    continue
                if len(parts) == 3 and parts[0] == "job" and parts[1].isdigit():
                    job = s.get(Job, int(parts[1]))
                    if job is None or job.status != queue.RUNNING:
                        shutil.rmtree(p, ignore_errors=True)
                elif parts[0] == "csa" and p.stat().st_mtime < day_ago:
                    shutil.rmtree(p, ignore_errors=True)

    def _unregister(self) -> None:
        queue.note_local_worker(self.id, False)
        try:
            with session_scope(self.services.sessions) as s:
                s.execute(update(WorkerRow).where(WorkerRow.id == self.id).values(stopped_at=utcnow(), current_job_id=None))
        except Exception:  # noqa: BLE001
            log.exception("could not mark worker %s stopped", self.id)
        log.info("worker %s stopped", self.id)

    def _beat(self, job_id: int | None) -> None:
        with session_scope(self.services.sessions) as s:
            s.execute(update(WorkerRow).where(WorkerRow.id == self.id).values(heartbeat_at=utcnow(), current_job_id=job_id))

    # -- one job -------------------------------------------------------------------------

    def run_once(self) -> bool:
        """Recover stale jobs, then claim and run one job; returns whether one ran."""
        self._beat(None)
        for job_id in queue.recover_stale_jobs(self.services.sessions, self.settings.max_attempts):
            log.warning("recovered job %s from a lost worker", job_id)
        kinds = runnable_kinds()
        if not kinds:
            return False
        job = queue.claim_next(self.services.sessions, self.id, self.settings.lease_seconds, kinds)
        if job is None:
            return False
        self._execute(job)
        return True

    def _execute(self, job: Job) -> None:
        self.current_job = job.id
        workdir = self.settings.resolved_work_dir / f"job-{job.id}-{uuid.uuid4().hex[:6]}"
        workdir.mkdir(parents=True, exist_ok=True)
        ctx = JobContext(self.services, job, self.id, workdir, self.stopping)
        beat_stop = threading.Event()
        beater = threading.Thread(target=self._heartbeat_loop, args=(ctx, beat_stop), daemon=True)
        beater.start()
        handler = JobLogHandler(ctx, threading.get_ident())
        logging.getLogger().addHandler(handler)
        log.info("job %s (%s) started", job.id, job.kind)
        try:
            KINDS[job.kind].run(ctx)
            if ctx.completed_result is None:
                raise RuntimeError(f"job kind {job.kind} returned without completing")
            log.info("job %s succeeded", job.id)
        except JobCancelled:
            self._end(ctx, queue.CANCELLED, "cancelled by request")
        except JobInterrupted as e:
            if not ctx.lost.is_set():
                queue.release_to_queue(self.services.sessions, job.id, self.id, str(e))
            log.warning("job %s interrupted: %s", job.id, e)
        except CSAInputError as e:
            self._end(ctx, queue.FAILED, str(e))
        except Exception as e:  # noqa: BLE001 - any failure of the job ends the job, not the worker
            ctx.log(traceback.format_exc(limit=20), "ERROR")
            self._end(ctx, queue.FAILED, f"{type(e).__name__}: {e}")
        finally:
            logging.getLogger().removeHandler(handler)
            beat_stop.set()
            beater.join(5)
            try:
                ctx.flush_logs()
            except Exception:  # noqa: BLE001
                log.exception("could not write the log of job %s", job.id)
            shutil.rmtree(workdir, ignore_errors=True)
            self.current_job = None

    def _end(self, ctx: JobContext, status: str, error: str) -> None:
        try:
            ctx.flush_logs()
            queue.finish(self.services.sessions, ctx.job_id, self.id, status, error=error)
        except queue.LostJob:
            log.warning("job %s was recovered by another worker before it ended", ctx.job_id)
        log.info("job %s %s: %s", ctx.job_id, status, error)

    def _heartbeat_loop(self, ctx: JobContext, stop: threading.Event) -> None:
        while not stop.wait(self.settings.heartbeat_seconds):
            try:
                if queue.heartbeat(self.services.sessions, ctx.job_id, self.id, self.settings.lease_seconds):
                    ctx.cancel_requested.set()
                self._beat(ctx.job_id)
            except queue.LostJob:
                ctx.lost.set()
                return
            except Exception:  # noqa: BLE001 - try again at the next beat
                log.exception("heartbeat of job %s failed", ctx.job_id)


def run_standalone(services: Services) -> int:
    """Run a worker in the foreground until SIGINT/SIGTERM (``csa worker``)."""
    worker = Worker(services, mode="standalone")

    def _stop(signum: int, _frame: object) -> None:
        log.info("signal %s: finishing the current step, then stopping", signum)
        worker.stopping.set()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    worker.run_forever()
    return 0

