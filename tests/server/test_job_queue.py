"""The job queue and the worker: lineage order, leases and recovery, cancellation, shutdown;
on SQLite and on PostgreSQL."""

from __future__ import annotations

import datetime as dt
import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import update

from server.db.models import Job, JobLog, LineageLock
from server.db.session import session_scope
from server.executors.embedded import EmbeddedExecutor as Worker
from server.jobs import queue
from server.jobs.context import JobContext
from server.jobs.kinds import KINDS
from server.services import Services, open_services
from tests.server.conftest import (
    ParamsInputs,
    ResultOutputs,
    both_backends,
    database_url,
    job_kind,
    test_settings,
)

pytestmark = both_backends

TEST_KIND = "count_steps"


@pytest.fixture
def services(request, tmp_path: Path, db_backend: str):
    url = database_url(request, db_backend)
    s = open_services(
        test_settings(
            tmp_path, database_url=url, lease_seconds=0.5, heartbeat_seconds=0.1, max_attempts=2
        )
    )
    yield s
    s.close()


def add_job(
    services: Services,
    lineage: str | None = None,
    kind: str = TEST_KIND,
    params: dict | None = None,
) -> int:
    with session_scope(services.sessions) as s:
        return queue.enqueue(s, kind, params or {"steps": 5}, lineage).id


def job(services: Services, job_id: int) -> Job:
    with session_scope(services.sessions) as s:
        return s.get(Job, job_id)


def compute_counting(inputs: ParamsInputs, workdir: Path, ctx: JobContext) -> ResultOutputs:
    """A test job: ``steps`` steps of 20 ms that report progress; ``fail_at`` raises."""
    steps = inputs.params.get("steps", 5)
    for i in range(steps):
        if inputs.params.get("fail_at") == i:
            raise RuntimeError("step exploded")
        ctx.progress(i / steps, f"step {i}", force=True)
        time.sleep(0.02)
    return ResultOutputs({"steps": steps})


@pytest.fixture
def counting_kind(monkeypatch):
    kind = job_kind(TEST_KIND, compute_counting)
    monkeypatch.setitem(KINDS, TEST_KIND, kind)
    return kind


def test_jobs_of_one_lineage_run_one_at_a_time_in_order(services: Services) -> None:
    a1 = add_job(services, "A")
    a2 = add_job(services, "A")
    b1 = add_job(services, "B")
    free = add_job(services, None)
    claimed = [queue.claim_next(services.sessions, "w1", 30, {TEST_KIND}) for _ in range(4)]
    assert [j.id if j else None for j in claimed] == [a1, b1, free, None]  # a2 waits for a1
    queue.finish(services.sessions, a1, "w1", queue.SUCCEEDED, result={})
    nxt = queue.claim_next(services.sessions, "w2", 30, {TEST_KIND})
    assert nxt is not None and nxt.id == a2


def test_a_worker_that_lost_its_job_cannot_finish_it(services: Services) -> None:
    j = add_job(services)
    queue.claim_next(services.sessions, "w1", 30, {TEST_KIND})
    with pytest.raises(queue.LostJob):
        queue.finish(services.sessions, j, "someone-else", queue.SUCCEEDED, result={})
    assert queue.renew_leases(services.sessions, "someone-else", 30) == (set(), set())
    assert queue.renew_leases(services.sessions, "w1", 30) == ({j}, set())


def test_expired_leases_are_requeued_then_failed_with_a_reason(services: Services) -> None:
    j = add_job(services, "L")
    for attempt in (1, 2):
        claimed = queue.claim_next(services.sessions, f"w{attempt}", 30, {TEST_KIND})
        assert claimed is not None and claimed.id == j and claimed.attempts == attempt
        assert (
            queue.recover_stale_jobs(services.sessions, max_attempts=2) == []
        )  # lease still valid
        with session_scope(services.sessions) as s:
            s.execute(
                update(Job).where(Job.id == j).values(lease_expires_at=dt.datetime(2000, 1, 1))
            )
        assert queue.recover_stale_jobs(services.sessions, max_attempts=2) == [j]
    final = job(services, j)
    assert (
        final.status == "failed"
        and "lease expired" in final.error
        and "attempt 2 of 2" in final.error
    )
    with session_scope(services.sessions) as s:
        assert s.get(LineageLock, "L") is None  # the lineage is free again
        messages = [m.message for m in s.query(JobLog).filter(JobLog.job_id == j)]
    assert any(m.startswith("re-queued after attempt 1 of 2") for m in messages)


def test_a_job_lost_with_its_worker_keeps_its_first_start(services: Services) -> None:
    """The second attempt of a job whose worker died: ``started_at`` stays the first start (the
    log has each attempt's start), the status line says the whole reason."""
    j = add_job(services)
    first = queue.claim_next(services.sessions, "w1", 30, {TEST_KIND})
    assert first is not None and first.started_at is not None
    with session_scope(services.sessions) as s:  # an hour ago, so a reset cannot look equal
        s.execute(
            update(Job)
            .where(Job.id == j)
            .values(started_at=first.started_at - dt.timedelta(hours=1))
        )
    reason = "its Ray worker was lost (NodeDiedError: The node died. It was killed.)"
    assert queue.attempt_lost(services.sessions, j, "w1", reason, max_attempts=2) == queue.QUEUED
    assert job(services, j).message == f"re-queued after attempt 1 of 2: {reason}"
    second = queue.claim_next(services.sessions, "w2", 30, {TEST_KIND})
    assert second is not None and second.attempts == 2
    assert second.started_at == first.started_at - dt.timedelta(hours=1)
    with session_scope(services.sessions) as s:
        starts = [
            m.message
            for m in s.query(JobLog).filter(JobLog.job_id == j).order_by(JobLog.id)
            if m.message.startswith("started")
        ]
    assert starts == ["started on worker w1 (attempt 1)", "started on worker w2 (attempt 2)"]


def test_cancel_a_queued_job(services: Services) -> None:
    j = add_job(services)
    with session_scope(services.sessions) as s:
        queue.request_cancel(s, s.get(Job, j))
    assert job(services, j).status == "cancelled"
    assert queue.claim_next(services.sessions, "w", 30, {TEST_KIND}) is None


def test_worker_runs_jobs_and_records_failures(services: Services, counting_kind) -> None:
    ok = add_job(services, params={"steps": 3})
    bad = add_job(services, params={"steps": 3, "fail_at": 1})
    worker = Worker(services)
    worker._register()
    assert worker.run_once() and worker.run_once() and not worker.run_once()
    assert job(services, ok).status == "succeeded" and job(services, ok).result == {"steps": 3}
    failed = job(services, bad)
    assert failed.status == "failed" and failed.error == "RuntimeError: step exploded"
    with session_scope(services.sessions) as s:
        log = [m.message for m in s.query(JobLog).filter(JobLog.job_id == bad)]
    assert any("Traceback" in m for m in log)


def test_cancelling_a_running_job_stops_it_at_its_next_step(
    services: Services, counting_kind
) -> None:
    j = add_job(services, params={"steps": 500})  # 10 s if nobody stops it
    worker = Worker(services)
    worker.start()
    try:
        deadline = time.monotonic() + 10
        while job(services, j).progress < 0.01 and time.monotonic() < deadline:
            time.sleep(0.02)
        with session_scope(services.sessions) as s:
            queue.request_cancel(s, s.get(Job, j))
        while job(services, j).status == "running" and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        worker.stop(timeout=10)
    final = job(services, j)
    assert final.status == "cancelled" and final.progress < 0.5 and final.result is None


def test_shutdown_hands_the_running_job_back(services: Services, counting_kind) -> None:
    j = add_job(services, "L", params={"steps": 500})
    worker = Worker(services)
    worker.start()
    deadline = time.monotonic() + 10
    while job(services, j).status != "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    worker.stop(timeout=10)
    back = job(services, j)
    assert back.status == "queued" and back.attempts == 0 and "shutting down" in back.message
    with session_scope(services.sessions) as s:
        assert s.get(LineageLock, "L") is None


def test_heartbeats_keep_a_long_job_alive(services: Services, counting_kind) -> None:
    """With a 0.5 s lease, a 1.5 s job survives because its heartbeat renews the lease,
    while a second worker keeps looking for stale jobs."""
    j = add_job(services, params={"steps": 75})
    worker = Worker(services)
    worker.start()
    other = Worker(services)
    other._register()
    stop = threading.Event()

    def reap() -> None:
        while not stop.is_set():
            queue.recover_stale_jobs(services.sessions, 2)
            time.sleep(0.05)

    reaper = threading.Thread(target=reap)
    reaper.start()
    try:
        deadline = time.monotonic() + 20
        while job(services, j).status in ("queued", "running") and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        reaper.join()
        worker.stop(timeout=10)
    final = job(services, j)
    assert final.status == "succeeded" and final.attempts == 1


def one_kind(monkeypatch, name: str, compute) -> str:
    monkeypatch.setitem(KINDS, name, job_kind(name, compute))
    return name


def test_a_renewal_that_began_before_the_claim_does_not_lose_the_job(
    services: Services, monkeypatch
) -> None:
    """The heartbeat thread renews leases while the executor thread claims a job: a renewal
    that began before the claim does not list the job, and must not count as its loss (on a
    loaded machine this once stranded a job as running with nobody on it)."""
    worker = Worker(services)
    worker._register()
    renewal_began = time.monotonic()

    def compute(inputs: ParamsInputs, workdir: Path, ctx: JobContext) -> ResultOutputs:
        worker.on_leases(set(), set(), renewal_began)  # its answer arrives after the claim
        ctx.progress(0.5, "half way", force=True)
        return ResultOutputs({"done": True})

    j = add_job(services, kind=one_kind(monkeypatch, "race", compute))
    assert worker.run_once()
    assert job(services, j).status == "succeeded" and job(services, j).result == {"done": True}


def test_a_job_seen_as_lost_but_still_owned_goes_back_to_the_queue(
    services: Services, monkeypatch
) -> None:
    """If the executor believes it lost a job the database still gives it, the job is handed
    back rather than left running forever (its lease would be renewed by every beat)."""
    worker = Worker(services)
    worker._register()

    def compute(inputs: ParamsInputs, workdir: Path, ctx: JobContext) -> ResultOutputs:
        worker.on_leases(
            set(), set(), time.monotonic()
        )  # a renewal after the claim, without the job
        ctx.progress(0.5, "half way", force=True)  # raises JobInterrupted
        return ResultOutputs({"done": True})

    j = add_job(services, kind=one_kind(monkeypatch, "seen_lost", compute))
    assert worker.run_once()
    back = job(services, j)
    assert (
        back.status == "queued"
        and back.worker_id is None
        and back.attempts == 0
        and back.result is None
    )
