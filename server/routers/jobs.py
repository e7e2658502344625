"""``/api/v1/jobs``: create, list, show, log, cancel, and a live progress stream (SSE)
(``server/services/jobs.py``)."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated

from fastapi import APIRouter, Body, Query, status
from fastapi.responses import StreamingResponse

from server.auth import OperatorScope
from server.deps import DbDep, ServicesDep, read_in_thread
from server.jobs.queue import TERMINAL
from server.quotas import QueuedJobsQuota
from server.schemas.common import ERROR_RESPONSES
from server.schemas.jobs import JobCreate, JobId, JobKindOut, JobLogOut, JobOut, JobStatus
from server.services import jobs

_KEEPALIVE_SECONDS = 15.0  # a comment line keeps proxies and clients from timing out

router = APIRouter(
    prefix="/jobs", tags=["jobs"], responses=ERROR_RESPONSES, dependencies=[OperatorScope]
)


@router.get(
    "/kinds",
    response_model=list[JobKindOut],
    summary="the job kinds and whether this build can run them",
)
def list_kinds() -> list[JobKindOut]:
    return jobs.list_kinds()


@router.post(
    "",
    response_model=JobOut,
    status_code=status.HTTP_202_ACCEPTED,
    dependencies=[QueuedJobsQuota],
    responses={
        409: ERROR_RESPONSES[422],
        501: {
            "model": ERROR_RESPONSES[422]["model"],
            "description": "the job kind is not available in this build",
        },
    },
)
def create_job(body: Annotated[JobCreate, Body(discriminator="kind")], db: DbDep) -> JobOut:
    """Queue a job. Kinds whose core code is missing from this build answer 501."""
    return jobs.create_job(db, body.kind, body.params)


@router.get("", response_model=list[JobOut])
def list_jobs(
    db: DbDep,
    status_: Annotated[JobStatus | None, Query(alias="status")] = None,
    kind: Annotated[str | None, Query(max_length=32, pattern=r"^[a-z_]+$")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[JobOut]:
    return jobs.list_jobs(db, status_, kind, limit)


@router.get("/{job_id}", response_model=JobOut)
def show_job(job_id: JobId, db: DbDep) -> JobOut:
    return jobs.show_job(db, job_id)


@router.get("/{job_id}/log", response_model=JobLogOut, summary="the last lines of the job's log")
def job_log(
    job_id: JobId, db: DbDep, tail: Annotated[int, Query(ge=1, le=10_000)] = 100
) -> JobLogOut:
    return jobs.job_log(db, job_id, tail)


@router.post("/{job_id}/cancel", response_model=JobOut, responses={409: ERROR_RESPONSES[422]})
def cancel_job(job_id: JobId, db: DbDep) -> JobOut:
    """Cancel a queued job at once, or ask a running one to stop at its next step."""
    return jobs.cancel_job(db, job_id)


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {"text/event-stream": {}},
            "description": "server-sent events: `progress` with the job as JSON, then `end`",
        }
    },
    summary="live progress as server-sent events",
)
async def job_events(job_id: JobId, db: DbDep, services: ServicesDep) -> StreamingResponse:
    # 404 for an unknown job, before the stream starts
    await read_in_thread(db, jobs.show_job, job_id)
    settings = services.settings

    async def stream():
        last: str | None = None
        deadline = time.monotonic() + settings.sse_max_seconds
        quiet_since = time.monotonic()
        yield "retry: 2000\n\n"
        while time.monotonic() < deadline:
            job = await asyncio.to_thread(jobs.job_snapshot, services.sessions, job_id)
            if job is None:
                yield 'event: end\ndata: {"status": "deleted"}\n\n'
                return
            data = job.model_dump_json()
            if data != last:
                last, quiet_since = data, time.monotonic()
                yield f"event: progress\ndata: {data}\n\n"
            elif time.monotonic() - quiet_since > _KEEPALIVE_SECONDS:
                quiet_since = time.monotonic()
                yield ": keep-alive\n\n"
            if job.status in TERMINAL:
                yield f"event: end\ndata: {json.dumps({'status': job.status})}\n\n"
                return
            await asyncio.sleep(settings.sse_poll_seconds)
        yield "event: timeout\ndata: {}\n\n"

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
