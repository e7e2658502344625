"""The job queue in the database: enqueue, claim, heartbeat, finish, cancel, recover.

Every state change is one conditional UPDATE (``... WHERE status = 'running' AND worker_id =
me``), so a worker that lost its lease can never overwrite what another worker did. Jobs of
one model lineage run one at a time, oldest first: a worker claims a lineage by inserting its
row in ``lineage_locks``, whose primary key makes the claim exclusive on any database.
"""

from __future__ import annotations

import datetime as dt
import os
import socket
from collections.abc import Callable
from typing import Any

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from server.db.models import Job, JobLog, LineageLock, Worker, utcnow
from server.db.session import session_scope

QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED = "queued", "running", "succeeded", "failed", "cancelled"
TERMINAL = frozenset({SUCCEEDED, FAILED, CANCELLED})
STATUSES = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED)


class LostJob(RuntimeError):
    """This worker no longer owns the job (its lease expired and the job was recovered)."""


def enqueue(session: Session, kind: str, params: dict[str, Any], lineage: str | None) -> Job:
    job = Job(kind=kind, params=params, lineage=lineage, status=QUEUED, message="queued")
    session.add(job)
    session.flush()
    return job


def append_log(session: Session, job_id: int, message: str, level: str = "INFO") -> None:
    session.add(JobLog(job_id=job_id, level=level, message=message[:4000]))


def trim_log(session: Session, job_id: int, keep: int) -> None:
    cutoff = session.scalar(select(JobLog.id).where(JobLog.job_id == job_id).order_by(JobLog.id.desc()).offset(keep).limit(1))
    if cutoff is not None:
        session.execute(delete(JobLog).where(JobLog.job_id == job_id, JobLog.id <= cutoff))


def claim_next(factory: sessionmaker[Session], worker_id: str, lease_seconds: float, kinds: set[str]) -> Job | None:
    """Mark the oldest runnable queued job as running for ``worker_id`` and return it."""
    with session_scope(factory) as s:
        candidates = s.scalars(select(Job).where(Job.status == QUEUED, Job.kind.in_(kinds)).order_by(Job.id).limit(50)).all()
    seen_lineages: set[str] = set()
    for job in candidates:
        if job.lineage is not None:
            if job.lineage in seen_lineages:
                continue  # an older job of this lineage goes first
            seen_lineages.add(job.lineage)
        now = utcnow()
        try:
            with session_scope(factory) as s:
                if job.lineage is not None:
                    s.add(LineageLock(lineage=job.lineage, job_id=job.id, acquired_at=now))
                    s.flush()
                res = s.execute(
                    update(Job)
                    .where(Job.id == job.id, Job.status == QUEUED)
                    .values(
                        status=RUNNING,
                        worker_id=worker_id,
                        attempts=Job.attempts + 1,
                        started_at=now,
                        heartbeat_at=now,
                        lease_expires_at=now + dt.timedelta(seconds=lease_seconds),
                        progress=0.0,
                        message="started",
                    )
                )
                if res.rowcount != 1:
                    raise LostJob("claimed by another worker")
                append_log(s, job.id, f"started on worker {worker_id}")
                claimed = s.get(Job, job.id)
                assert claimed is not None
            return claimed
        except (IntegrityError, LostJob):
            continue
    return None


def heartbeat(factory: sessionmaker[Session], job_id: int, worker_id: str, lease_seconds: float) -> bool:
    """Extend the lease; returns whether cancellation was requested. Raises :class:`LostJob`."""
    now = utcnow()
    with session_scope(factory) as s:
        res = s.execute(
            update(Job)
            .where(Job.id == job_id, Job.worker_id == worker_id, Job.status == RUNNING)
            .values(heartbeat_at=now, lease_expires_at=now + dt.timedelta(seconds=lease_seconds))
        )
        if res.rowcount != 1:
            raise LostJob(f"job {job_id} is no longer running on worker {worker_id}")
        return bool(s.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


def report_progress(factory: sessionmaker[Session], job_id: int, worker_id: str, progress: float | None, message: str | None) -> bool:
    """Record progress; returns whether cancellation was requested. Raises :class:`LostJob`."""
    values: dict[str, Any] = {}
    if progress is not None:
        values["progress"] = max(0.0, min(1.0, float(progress)))
    if message is not None:
        values["message"] = message[:1000]
    with session_scope(factory) as s:
        if values:
            res = s.execute(update(Job).where(Job.id == job_id, Job.worker_id == worker_id, Job.status == RUNNING).values(**values))
            if res.rowcount != 1:
                raise LostJob(f"job {job_id} is no longer running on worker {worker_id}")
        return bool(s.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


def _release_lineage(s: Session, job: Job) -> None:
    if job.lineage is not None:
        s.execute(delete(LineageLock).where(LineageLock.lineage == job.lineage, LineageLock.job_id == job.id))


def finish(
    factory: sessionmaker[Session],
    job_id: int,
    worker_id: str,
    status: str,
    result: dict[str, Any] | None = None,
    error: str | None = None,
    register: Callable[[Session], dict[str, Any]] | None = None,
) -> dict[str, Any] | None:
    """End a job this worker owns; ``register`` adds the job's outputs (model versions, memory
    bank entries) in the same transaction, so outputs exist exactly when the job succeeded."""
    with session_scope(factory) as s:
        job = s.get(Job, job_id)
        if job is None or job.status != RUNNING or job.worker_id != worker_id:
            raise LostJob(f"job {job_id} is no longer running on worker {worker_id}")
        if register is not None:
            result = register(s)
        now = utcnow()
        res = s.execute(
            update(Job)
            .where(Job.id == job_id, Job.worker_id == worker_id, Job.status == RUNNING)
            .values(
                status=status,
                result=result,
                error=error,
                finished_at=now,
                lease_expires_at=None,
                progress=1.0 if status == SUCCEEDED else Job.progress,
                message={SUCCEEDED: "done", FAILED: "failed", CANCELLED: "cancelled"}.get(status, status),
            )
        )
        if res.rowcount != 1:
            raise LostJob(f"job {job_id} is no longer running on worker {worker_id}")
        _release_lineage(s, job)
        append_log(s, job_id, f"{status}" + (f": {error}" if error else ""), "ERROR" if status == FAILED else "INFO")
    return result


def release_to_queue(factory: sessionmaker[Session], job_id: int, worker_id: str, reason: str) -> None:
    """Give a running job back (worker shutting down); the attempt does not count."""
    with session_scope(factory) as s:
        job = s.get(Job, job_id)
        if job is None or job.status != RUNNING or job.worker_id != worker_id:
            return
        if job.cancel_requested:
            job.status, job.finished_at, job.error, job.message = CANCELLED, utcnow(), "cancelled by request", "cancelled"
        else:
            job.status, job.message = QUEUED, f"re-queued: {reason}"
            job.attempts = max(0, job.attempts - 1)
        job.worker_id, job.lease_expires_at = None, None
        _release_lineage(s, job)
        append_log(s, job_id, job.message, "WARNING")


def request_cancel(session: Session, job: Job) -> Job:
    """Cancel a queued job now; ask a running one to stop at its next check."""
    if job.status == QUEUED:
        job.status, job.finished_at, job.message, job.error = CANCELLED, utcnow(), "cancelled", "cancelled by request"
        append_log(session, job.id, "cancelled before it started")
    elif job.status == RUNNING:
        job.cancel_requested = True
        job.message = "cancelling"
        append_log(session, job.id, "cancellation requested")
    session.flush()
    return job


# -- recovery of jobs whose worker died ---------------------------------------------------

_LOCAL_WORKERS: set[str] = set()  # worker ids alive in this process


def note_local_worker(worker_id: str, alive: bool) -> None:
    (_LOCAL_WORKERS.add if alive else _LOCAL_WORKERS.discard)(worker_id)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _owner_gone(w: Worker | None, worker_id: str | None) -> str | None:
    """Why the owning worker is certainly dead (same host, process gone), or None if unknown."""
    if w is None or w.hostname != socket.gethostname():
        return None
    if w.stopped_at is not None:
        return f"worker {worker_id} stopped"
    if w.pid == os.getpid() and worker_id not in _LOCAL_WORKERS:
        return f"worker {worker_id} (pid {w.pid}) no longer exists (this process restarted)"
    if w.pid != os.getpid() and not _pid_alive(w.pid):
        return f"worker {worker_id} (pid {w.pid}) is gone"
    return None


def recover_stale_jobs(factory: sessionmaker[Session], max_attempts: int) -> list[int]:
    """Re-queue (or fail, after ``max_attempts``) running jobs whose worker died: its lease
    expired, or it was a process on this host that no longer exists. Returns their ids."""
    now = utcnow()
    recovered: list[int] = []
    with session_scope(factory) as s:
        running = s.scalars(select(Job).where(Job.status == RUNNING)).all()
        for job in running:
            owner = s.get(Worker, job.worker_id) if job.worker_id else None
            reason = _owner_gone(owner, job.worker_id)
            if reason is None and job.lease_expires_at is not None and job.lease_expires_at < now:
                reason = f"worker {job.worker_id} stopped sending heartbeats (lease expired at {job.lease_expires_at.isoformat(timespec='seconds')}Z)"
            if reason is None:
                continue
            res_values: dict[str, Any]
            if job.cancel_requested:
                res_values = {"status": CANCELLED, "finished_at": now, "error": "cancelled by request", "message": "cancelled"}
                note = f"cancelled: {reason} while cancelling"
            elif job.attempts >= max_attempts:
                msg = f"{reason} during attempt {job.attempts} of {max_attempts}; not retried"
                res_values = {"status": FAILED, "finished_at": now, "error": msg, "message": "failed"}
                note = f"failed: {msg}"
            else:
                msg = f"re-queued after attempt {job.attempts} of {max_attempts}: {reason}"
                res_values = {"status": QUEUED, "message": msg}
                note = msg
            res = s.execute(
                update(Job)
                .where(Job.id == job.id, Job.status == RUNNING, Job.worker_id == job.worker_id)
                .values(worker_id=None, lease_expires_at=None, **res_values)
            )
            if res.rowcount == 1:
                _release_lineage(s, job)
                append_log(s, job.id, note, "WARNING")
                recovered.append(job.id)
        # Locks are released with every state change; this only guards against manual edits.
        running_ids = select(Job.id).where(Job.status == RUNNING)
        s.execute(delete(LineageLock).where(LineageLock.job_id.not_in(running_ids)))
    return recovered
