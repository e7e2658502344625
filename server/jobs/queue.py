"""The job queue in the database: enqueue, claim, leases, progress, finish, cancel, recover.

A job runs under an *owner*: the executor of one API process (``server/executors``), which
runs it in the process (embedded) or hands it to a Ray cluster. Every state change is one
conditional UPDATE (``... WHERE status = 'running' AND worker_id = owner``), so an owner that
lost a job can never overwrite what happened to it since. Jobs of one model lineage run one
at a time, oldest first: an owner claims a lineage by inserting its row in ``lineage_locks``,
whose primary key makes the claim exclusive on any database, whichever API process claims.

The owner renews the leases of all its running jobs from one heartbeat. A running job whose
owner is gone (a process of this host that no longer exists, or a lease that expired) is
re-queued by the next executor that looks, or failed with the reason after
``max_attempts`` attempts: so restarting the API never leaves a job ``running`` forever.
"""

from __future__ import annotations

import datetime as dt
import os
import re
import socket
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from server import faults
from server.db.models import Job, JobLog, LineageLock, Worker, utcnow
from server.db.session import session_scope

QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED = (
    "queued",
    "running",
    "succeeded",
    "failed",
    "cancelled",
)
TERMINAL = frozenset({SUCCEEDED, FAILED, CANCELLED})
STATUSES = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED)


class LostJob(RuntimeError):
    """This owner no longer owns the job (it was recovered, re-queued or ended meanwhile)."""


def enqueue(session: Session, kind: str, params: dict[str, Any], lineage: str | None) -> Job:
    job = Job(kind=kind, params=params, lineage=lineage, status=QUEUED, message="queued")
    session.add(job)
    session.flush()
    return job


def brief(text: str, limit: int) -> str:
    """``text`` shortened to at most ``limit`` characters for a status line or a table cell:
    its first line, as many whole sentences of it as fit, else cut at a word with an
    ellipsis, so that nothing is cut off mid-sentence without saying so."""
    line = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
    if len(line) <= limit:
        return line
    sentences = re.split(r"(?<=[.!?])\s+", line)
    kept = ""
    for sentence in sentences:
        candidate = f"{kept} {sentence}".strip()
        if len(candidate) > limit:
            break
        kept = candidate
    if kept:
        return kept
    cut = line[: limit - 1]
    space = cut.rfind(" ")
    return (cut[:space] if space > limit // 2 else cut).rstrip(" ,;:") + "…"


def append_log(session: Session, job_id: int, message: str, level: str = "INFO") -> None:
    session.add(JobLog(job_id=job_id, level=level, message=message[:4000]))


def trim_log(session: Session, job_id: int, keep: int) -> None:
    cutoff = session.scalar(
        select(JobLog.id)
        .where(JobLog.job_id == job_id)
        .order_by(JobLog.id.desc())
        .offset(keep)
        .limit(1)
    )
    if cutoff is not None:
        session.execute(delete(JobLog).where(JobLog.job_id == job_id, JobLog.id <= cutoff))


def claim_next(
    factory: sessionmaker[Session], owner: str, lease_seconds: float, kinds: set[str]
) -> Job | None:
    """Mark the oldest runnable queued job as running for ``owner`` and return it."""
    with session_scope(factory) as s:
        candidates = s.scalars(
            select(Job).where(Job.status == QUEUED, Job.kind.in_(kinds)).order_by(Job.id).limit(50)
        ).all()
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
                        worker_id=owner,
                        attempts=Job.attempts + 1,
                        # The first attempt's start: a retried job keeps it (each attempt's
                        # start is in the log: "started on worker ... (attempt n)").
                        started_at=func.coalesce(Job.started_at, now),
                        heartbeat_at=now,
                        lease_expires_at=now + dt.timedelta(seconds=lease_seconds),
                        progress=0.0,
                        message="started",
                    )
                )
                if res.rowcount != 1:
                    raise LostJob("claimed by another owner")
                claimed = s.get(Job, job.id)
                assert claimed is not None
                append_log(s, job.id, f"started on worker {owner} (attempt {claimed.attempts})")
            return claimed
        except (IntegrityError, LostJob):
            continue
    return None


def renew_leases(
    factory: sessionmaker[Session], owner: str, lease_seconds: float
) -> tuple[set[int], set[int]]:
    """Extend the lease of every job ``owner`` runs; returns (the ids it still owns, those of
    them whose cancellation was requested). A job missing from the first set was lost."""
    now = utcnow()
    with session_scope(factory) as s:
        s.execute(
            update(Job)
            .where(Job.worker_id == owner, Job.status == RUNNING)
            .values(heartbeat_at=now, lease_expires_at=now + dt.timedelta(seconds=lease_seconds))
        )
        rows = s.execute(
            select(Job.id, Job.cancel_requested).where(
                Job.worker_id == owner, Job.status == RUNNING
            )
        ).all()
    return {job_id for job_id, _ in rows}, {job_id for job_id, cancel in rows if cancel}


def report(
    factory: sessionmaker[Session],
    job_id: int,
    owner: str,
    progress: float | None = None,
    message: str | None = None,
    logs: Iterable[tuple[str, str]] = (),
    keep_log_lines: int | None = None,
) -> bool:
    """Record a running job's progress, status line and log lines (``(level, message)``) in
    one transaction; returns whether cancellation was requested. Raises :class:`LostJob`
    (after keeping the log lines) when ``owner`` no longer runs the job."""
    values: dict[str, Any] = {}
    if progress is not None:
        values["progress"] = max(0.0, min(1.0, float(progress)))
    if message is not None:
        values["message"] = message[:1000]
    lost = False
    with session_scope(factory) as s:
        if values:
            res = s.execute(
                update(Job)
                .where(Job.id == job_id, Job.worker_id == owner, Job.status == RUNNING)
                .values(**values)
            )
            lost = res.rowcount != 1
        lines = list(logs)
        for level, line in lines:
            append_log(s, job_id, line, level)
        if lines and keep_log_lines is not None:
            trim_log(s, job_id, keep_log_lines)
        cancel = bool(s.scalar(select(Job.cancel_requested).where(Job.id == job_id)))
    if lost:
        raise LostJob(f"job {job_id} is no longer running under {owner}")
    return cancel


def _release_lineage(s: Session, job: Job) -> None:
    if job.lineage is not None:
        s.execute(
            delete(LineageLock).where(
                LineageLock.lineage == job.lineage, LineageLock.job_id == job.id
            )
        )


def finish(
    factory: sessionmaker[Session],
    job_id: int,
    owner: str,
    status: str,
    result: dict[str, Any] | None = None,
    error: str | None = None,
    register: Callable[[Session], dict[str, Any]] | None = None,
) -> dict[str, Any] | None:
    """End a job ``owner`` runs; ``register`` adds the job's outputs (model versions, memory
    bank entries) in the same transaction, so outputs exist exactly when the job succeeded."""
    with session_scope(factory) as s:
        job = s.get(Job, job_id)
        if job is None or job.status != RUNNING or job.worker_id != owner:
            raise LostJob(f"job {job_id} is no longer running under {owner}")
        if register is not None:
            result = register(s)
            faults.point("job.registering")
        now = utcnow()
        res = s.execute(
            update(Job)
            .where(Job.id == job_id, Job.worker_id == owner, Job.status == RUNNING)
            .values(
                status=status,
                result=result,
                error=error,
                finished_at=now,
                lease_expires_at=None,
                progress=1.0 if status == SUCCEEDED else Job.progress,
                message={SUCCEEDED: "done", FAILED: "failed", CANCELLED: "cancelled"}.get(
                    status, status
                ),
            )
        )
        if res.rowcount != 1:
            raise LostJob(f"job {job_id} is no longer running under {owner}")
        _release_lineage(s, job)
        append_log(
            s,
            job_id,
            f"{status}" + (f": {error}" if error else ""),
            "ERROR" if status == FAILED else "INFO",
        )
    return result


def release_to_queue(factory: sessionmaker[Session], job_id: int, owner: str, reason: str) -> None:
    """Give a running job back (its owner is shutting down); the attempt does not count."""
    with session_scope(factory) as s:
        job = s.get(Job, job_id)
        if job is None or job.status != RUNNING or job.worker_id != owner:
            return
        if job.cancel_requested:
            job.status, job.finished_at, job.error, job.message = (
                CANCELLED,
                utcnow(),
                "cancelled by request",
                "cancelled",
            )
        else:
            job.status, job.message = QUEUED, f"re-queued: {reason}"
            job.attempts = max(0, job.attempts - 1)
        job.worker_id, job.lease_expires_at = None, None
        _release_lineage(s, job)
        append_log(s, job_id, job.message, "WARNING")


def _after_lost_attempt(
    job: Job, reason: str, max_attempts: int, now: dt.datetime
) -> tuple[dict[str, Any], str]:
    """What becomes of a running job whose attempt was lost (owner or Ray worker died):
    cancelled if that was asked, failed after ``max_attempts`` attempts, else queued again.
    Returns the column values and the log line."""
    if job.cancel_requested:
        return {
            "status": CANCELLED,
            "finished_at": now,
            "error": "cancelled by request",
            "message": "cancelled",
        }, f"cancelled: {reason} while cancelling"
    if job.attempts >= max_attempts:
        msg = f"{reason} during attempt {job.attempts} of {max_attempts}; not retried"
        return {
            "status": FAILED,
            "finished_at": now,
            "error": msg,
            "message": "failed",
        }, f"failed: {msg}"
    msg = f"re-queued after attempt {job.attempts} of {max_attempts}: {reason}"
    return {"status": QUEUED, "message": msg}, msg


def _end_lost_attempt(s: Session, job: Job, reason: str, max_attempts: int) -> bool:
    values, note = _after_lost_attempt(job, reason, max_attempts, utcnow())
    res = s.execute(
        update(Job)
        .where(Job.id == job.id, Job.status == RUNNING, Job.worker_id == job.worker_id)
        .values(worker_id=None, lease_expires_at=None, **values)
    )
    if res.rowcount != 1:
        return False
    _release_lineage(s, job)
    append_log(s, job.id, note, "WARNING" if values["status"] != FAILED else "ERROR")
    return True


def attempt_lost(
    factory: sessionmaker[Session], job_id: int, owner: str, reason: str, max_attempts: int
) -> str | None:
    """An attempt of a job ``owner`` runs died with its process (a Ray worker or node):
    re-queue the job, or fail it after ``max_attempts``. Returns the job's new status (None
    if ``owner`` no longer ran it)."""
    with session_scope(factory) as s:
        job = s.get(Job, job_id)
        if job is None or job.status != RUNNING or job.worker_id != owner:
            return None
        if not _end_lost_attempt(s, job, reason, max_attempts):
            return None
        s.flush()
        s.refresh(job)
        return job.status


def request_cancel(session: Session, job: Job) -> Job:
    """Cancel a queued job now; ask a running one to stop at its next check."""
    if job.status == QUEUED:
        job.status, job.finished_at, job.message, job.error = (
            CANCELLED,
            utcnow(),
            "cancelled",
            "cancelled by request",
        )
        append_log(session, job.id, "cancelled before it started")
    elif job.status == RUNNING:
        job.cancel_requested = True
        job.message = "cancelling"
        append_log(session, job.id, "cancellation requested")
    session.flush()
    return job


# -- recovery of jobs whose owner died ----------------------------------------------------

_LOCAL_OWNERS: set[str] = set()  # owner ids alive in this process


def note_local_owner(owner: str, alive: bool) -> None:
    (_LOCAL_OWNERS.add if alive else _LOCAL_OWNERS.discard)(owner)


def pid_alive(pid: int) -> bool:
    """Whether a process of this host with ``pid`` runs (one of another user counts; a zombie,
    killed but not yet reaped by its parent, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True  # no /proc (not Linux): the signal said it exists
    return stat.rpartition(")")[2].split()[:1] != ["Z"]


def _owner_gone(w: Worker | None, owner: str | None) -> str | None:
    """Why the owner is certainly dead (a process of this host that is gone), or None if unknown."""
    if w is None or w.hostname != socket.gethostname():
        return None
    if w.stopped_at is not None:
        return f"{owner} stopped"
    if w.pid == os.getpid() and owner not in _LOCAL_OWNERS:
        return f"{owner} (pid {w.pid}) no longer exists (this process restarted)"
    if w.pid != os.getpid() and not pid_alive(w.pid):
        return f"{owner} (pid {w.pid}) is gone"
    return None


def stale_jobs(s: Session) -> list[tuple[Job, str]]:
    """Running jobs whose owner died, with the reason: its lease expired, or it was a process
    on this host that no longer exists (what :func:`recover_stale_jobs` ends; ``csa doctor``
    lists them)."""
    now = utcnow()
    found: list[tuple[Job, str]] = []
    for job in s.scalars(select(Job).where(Job.status == RUNNING).order_by(Job.id)).all():
        owner = s.get(Worker, job.worker_id) if job.worker_id else None
        reason = _owner_gone(owner, job.worker_id)
        if reason is None and job.lease_expires_at is not None and job.lease_expires_at < now:
            reason = (
                f"lease expired at {job.lease_expires_at.isoformat(timespec='seconds')}Z "
                f"({job.worker_id} stopped renewing it)"
            )
        if reason is not None:
            found.append((job, reason))
    return found


def recover_stale_jobs(factory: sessionmaker[Session], max_attempts: int) -> list[int]:
    """Re-queue (or fail, after ``max_attempts``) running jobs whose owner died
    (:func:`stale_jobs`). Returns their ids."""
    recovered: list[int] = []
    with session_scope(factory) as s:
        for job, reason in stale_jobs(s):
            if _end_lost_attempt(s, job, reason, max_attempts):
                recovered.append(job.id)
        # Locks are released with every state change; this only guards against manual edits.
        running_ids = select(Job.id).where(Job.status == RUNNING)
        s.execute(delete(LineageLock).where(LineageLock.job_id.not_in(running_ids)))
    return recovered
