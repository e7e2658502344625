"""``/api/v1/jobs``: create, list, show, log, cancel, and a live progress stream (SSE)."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated

from fastapi import APIRouter, Body, Path, Query, status
from fastapi.responses import StreamingResponse
from sqlalchemy import select

from server.auth import OperatorScope
from server.db.models import MAX_ID, Job, JobLog
from server.db.session import session_scope
from server.deps import DbDep, ServicesDep
from server.errors import APIError, not_available
from server.jobs import queue
from server.jobs.kinds import KINDS
from server.lookups import get_job
from server.quotas import QueuedJobsQuota
from server.schemas.common import ERROR_RESPONSES
from server.schemas.jobs import JobCreate, JobKindOut, JobLogLine, JobLogOut, JobOut, JobStatus

_KEEPALIVE_SECONDS = 15.0  # a comment line keeps proxies and clients from timing out

JobId = Annotated[int, Path(ge=1, le=MAX_ID)]

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=ERROR_RESPONSES, dependencies=[OperatorScope])


@router.get("/kinds", response_model=list[JobKindOut], summary="the job kinds and whether this build can run them")
def list_kinds() -> list[JobKindOut]:
    out = []
    for kind in KINDS.values():
        reason = kind.missing_reason()
        out.append(JobKindOut(kind=kind.name, description=kind.description, available=reason is None, reason=reason))
    return out


@router.post(
    "",
    response_model=JobOut,
    status_code=status.HTTP_202_ACCEPTED,
    dependencies=[QueuedJobsQuota],
    responses={409: ERROR_RESPONSES[422], 501: {"model": ERROR_RESPONSES[422]["model"], "description": "the job kind is not available in this build"}},
)
def create_job(body: Annotated[JobCreate, Body(discriminator="kind")], db: DbDep) -> JobOut:
    """Queue a job. Kinds whose core code is missing from this build answer 501."""
    kind = KINDS[body.kind]
    reason = kind.missing_reason()
    if reason is not None:
        raise not_available(f"job kind {kind.name!r}: {reason}")
    job = queue.enqueue(db, kind.name, {}, None)
    params, lineage = kind.prepare(db, body.params, job)
    job.params, job.lineage = params, lineage
    queue.append_log(db, job.id, f"queued {kind.name}")
    db.commit()
    return JobOut.model_validate(job)


@router.get("", response_model=list[JobOut])
def list_jobs(
    db: DbDep,
    status_: Annotated[JobStatus | None, Query(alias="status")] = None,
    kind: Annotated[str | None, Query(max_length=32, pattern=r"^[a-z_]+$")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[JobOut]:
    q = select(Job).order_by(Job.id.desc()).limit(limit)
    if status_ is not None:
        q = q.where(Job.status == status_)
    if kind is not None:
        q = q.where(Job.kind == kind)
    return [JobOut.model_validate(j) for j in db.scalars(q)]


@router.get("/{job_id}", response_model=JobOut)
def show_job(job_id: JobId, db: DbDep) -> JobOut:
    return JobOut.model_validate(get_job(db, job_id))


@router.get("/{job_id}/log", response_model=JobLogOut, summary="the last lines of the job's log")
def job_log(job_id: JobId, db: DbDep, tail: Annotated[int, Query(ge=1, le=10_000)] = 100) -> JobLogOut:
    get_job(db, job_id)
    rows = db.scalars(select(JobLog).where(JobLog.job_id == job_id).order_by(JobLog.id.desc()).limit(tail)).all()
    return JobLogOut(job_id=job_id, lines=[JobLogLine(time=r.created_at, level=r.level, message=r.message) for r in reversed(rows)])


@router.post("/{job_id}/cancel", response_model=JobOut, responses={409: ERROR_RESPONSES[422]})
def cancel_job(job_id: JobId, db: DbDep) -> JobOut:
    """Cancel a queued job at once, or ask a running one to stop at its next step."""
    job = get_job(db, job_id)
    if job.status in queue.TERMINAL:
        raise APIError(409, "conflict", f"job {job_id} already ended ({job.status})")
    queue.request_cancel(db, job)
    db.commit()
    return JobOut.model_validate(job)


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "server-sent events: `progress` with the job as JSON, then `end`"}},
    summary="live progress as server-sent events",
)
async def job_events(job_id: JobId, db: DbDep, services: ServicesDep) -> StreamingResponse:
    get_job(db, job_id)
    db.close()
    settings = services.settings

    def snapshot() -> JobOut | None:
        with session_scope(services.sessions) as s:
            job = s.get(Job, job_id)
            return JobOut.model_validate(job) if job is not None else None

    async def stream():
        last: str | None = None
        deadline = time.monotonic() + settings.sse_max_seconds
        quiet_since = time.monotonic()
        yield "retry: 2000\n\n"
        while time.monotonic() < deadline:
            job = await asyncio.to_thread(snapshot)
            if job is None:
                yield "event: end\ndata: {\"status\": \"deleted\"}\n\n"
                return
            data = job.model_dump_json()
            if data != last:
                last, quiet_since = data, time.monotonic()
                yield f"event: progress\ndata: {data}\n\n"
            elif time.monotonic() - quiet_since > _KEEPALIVE_SECONDS:
                quiet_since = time.monotonic()
                yield ": keep-alive\n\n"
            if job.status in queue.TERMINAL:
                yield f"event: end\ndata: {json.dumps({'status': job.status})}\n\n"
                return
            await asyncio.sleep(settings.sse_poll_seconds)
        yield "event: timeout\ndata: {}\n\n"

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
