"""Jobs: the kinds this build can run, queueing, listing, logs, cancelling and retrying
(``/api/v1/jobs``, the dashboard's job pages). What runs a job and how its state changes are
``server/jobs`` (the kinds, the queue) and ``server/executors``."""

from __future__ import annotations

from pydantic import BaseModel
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.db.models import Job, JobLog
from server.db.session import session_scope
from server.errors import APIError, conflict, not_available
from server.jobs import queue
from server.jobs.kinds import KINDS
from server.lookups import get_job
from server.registry import root_conflict
from server.schemas.jobs import JobKindOut, JobLogLine, JobLogOut, JobOut


def list_kinds() -> list[JobKindOut]:
    """Every job kind and whether this build can run it (and why not)."""
    out = []
    for kind in KINDS.values():
        reason = kind.missing_reason()
        out.append(
            JobKindOut(
                kind=kind.name,
                description=kind.description,
                available=reason is None,
                reason=reason,
            )
        )
    return out


def create_job(db: Session, kind_name: str, params: BaseModel) -> JobOut:
    """Queue a job of a known kind, its references resolved to ids (4xx for a wrong one);
    501 for a kind whose core code is missing from this build."""
    kind = KINDS[kind_name]
    reason = kind.missing_reason()
    if reason is not None:
        raise not_available(f"job kind {kind.name!r}: {reason}")
    job = queue.enqueue(db, kind.name, {}, None)
    job.params, job.lineage = kind.prepare(db, params, job)
    queue.append_log(db, job.id, f"queued {kind.name}")
    db.commit()
    return JobOut.model_validate(job)


def list_jobs(
    db: Session, status: str | None = None, kind: str | None = None, limit: int = 100
) -> list[JobOut]:
    """The newest ``limit`` jobs (of ``status``, of ``kind``), newest first."""
    q = select(Job).order_by(Job.id.desc()).limit(limit)
    if status is not None:
        q = q.where(Job.status == status)
    if kind is not None:
        q = q.where(Job.kind == kind)
    return [JobOut.model_validate(j) for j in db.scalars(q)]


def show_job(db: Session, job_id: int) -> JobOut:
    return JobOut.model_validate(get_job(db, job_id))


def job_log(db: Session, job_id: int, tail: int = 100) -> JobLogOut:
    """The last ``tail`` lines of a job's log, oldest first."""
    get_job(db, job_id)
    newest = select(JobLog).where(JobLog.job_id == job_id).order_by(JobLog.id.desc()).limit(tail)
    rows = db.scalars(newest).all()
    lines = [JobLogLine(time=r.created_at, level=r.level, message=r.message) for r in rows]
    return JobLogOut(job_id=job_id, lines=lines[::-1])


def job_snapshot(sessions: sessionmaker[Session], job_id: int) -> JobOut | None:
    """The job as it is now, in a session of its own (a live stream outlasts its request's
    session); None once it is deleted."""
    with session_scope(sessions) as s:
        job = s.get(Job, job_id)
        return JobOut.model_validate(job) if job is not None else None


def cancel_job(db: Session, job_id: int) -> JobOut:
    """Cancel a queued job at once, or ask a running one to stop at its next step; 409 for a
    job that already ended."""
    job = get_job(db, job_id)
    if job.status in queue.TERMINAL:
        raise APIError(409, "conflict", f"job {job_id} already ended ({job.status})")
    queue.request_cancel(db, job)
    db.commit()
    return JobOut.model_validate(job)


def retry_job(db: Session, job_id: int) -> JobOut:
    """Queue a failed (or cancelled) job again: a new job of the same kind with the same
    resolved parameters; both logs name the other."""
    job = get_job(db, job_id)
    if job.status not in (queue.FAILED, queue.CANCELLED):
        raise conflict(f"job {job_id} is {job.status}; only failed or cancelled jobs are retried")
    kind = KINDS.get(job.kind)
    if kind is None:
        raise APIError(
            422, "invalid", f"job {job_id} has kind {job.kind!r}, which this build does not know"
        )
    reason = kind.missing_reason()
    if reason is not None:
        raise not_available(f"job kind {kind.name!r}: {reason}")
    if kind.name == "pretrain":  # the copy registers the same name and lineage root: still free?
        name, lineage = (job.params or {}).get("name", ""), job.lineage or ""
        taken = root_conflict(db, name, lineage, "a pre-training")
        if taken is not None:
            raise conflict(taken[1], field=f"params.{taken[0]}")
    again = queue.enqueue(db, job.kind, dict(job.params or {}), job.lineage)
    queue.append_log(db, again.id, f"retry of job {job.id}")
    queue.append_log(db, job.id, f"retried as job {again.id}")
    db.commit()
    return JobOut.model_validate(again)
