"""The embedded executor (``CSA_EXECUTOR=embedded``, the default): jobs run one at a time in
a thread of the API process, against its own database and artifact store: the job's three
phases (``server/jobs/phases.py``) one after another in that thread, ``gather`` and
``register`` in transactions of their own (``register`` in the one that ends the job), and
``compute`` in between, on the Inputs and files ``gather`` named.

Nothing else needs to be started. A job whose lease this executor stops renewing (the API
process was killed) is re-queued when the API starts again (``queue.recover_stale_jobs``),
or failed with the reason after ``CSA_MAX_ATTEMPTS`` attempts; on a clean shutdown the
running job is handed back to the queue without counting the attempt.
"""

from __future__ import annotations

import logging
import shutil
import time

from server.db.models import Job
from server.db.session import session_scope
from server.executors.base import INTERRUPTED, Executor, run_job_function
from server.jobs import queue
from server.jobs.context import JobContext, LocalJobContext
from server.jobs.kinds import KINDS, runnable_kinds
from server.jobs.phases import ApiNode, compute_outputs, gather_inputs

log = logging.getLogger(__name__)


class EmbeddedExecutor(Executor):
    mode = "embedded"

    def __init__(self, services):
        super().__init__(services)
        self._ctx: LocalJobContext | None = None
        self._claimed_at = float("inf")

    def open(self) -> None:
        if self.settings.torch_threads:
            import torch

            torch.set_num_threads(self.settings.torch_threads)

    def current_job(self) -> int | None:
        ctx = self._ctx
        return ctx.job_id if ctx is not None else None

    def on_leases(self, owned: set[int], cancel: set[int], since: float) -> None:
        ctx, claimed_at = self._ctx, self._claimed_at
        if ctx is None or claimed_at > since:
            return  # no job, or one claimed after the renewal began: the next beat tells
        if ctx.job_id not in owned:
            ctx.lost.set()
        elif ctx.job_id in cancel:
            ctx.cancel_requested.set()

    def step(self) -> bool:
        return self.run_once()

    def run_once(self) -> bool:
        """Recover jobs of dead owners, then claim and run one job; returns whether one ran."""
        self.recover()
        kinds = runnable_kinds()
        if not kinds:
            return False
        job = queue.claim_next(self.services.sessions, self.id, self.settings.lease_seconds, kinds)
        if job is None:
            return False
        self._claimed_at = time.monotonic()  # the claim is committed by now
        self._execute(job)
        return True

    def _execute(self, job: Job) -> None:
        workdir = self.settings.resolved_work_dir / self.scratch_folder(job.id)
        workdir.mkdir(parents=True, exist_ok=True)
        ctx = LocalJobContext(self.services, job, self.id, workdir, self.stopping)
        self._ctx = ctx
        kind, params, node = (
            KINDS[job.kind],
            dict(job.params or {}),
            ApiNode(job.id, self.services.store),
        )

        def phases(_: JobContext) -> None:
            with session_scope(self.services.sessions) as s:
                inputs = gather_inputs(kind.gather, s, params, node)
            outputs = compute_outputs(kind.compute, inputs, workdir, ctx)
            ctx.finish(lambda s: kind.register(s, outputs, node))

        log.info("job %s (%s) started", job.id, job.kind)
        try:
            status, error = run_job_function(ctx, phases)
            if status == INTERRUPTED:
                # Also when it was lost: if the database still gives it to this executor (the
                # loss was only seen, not real), it must not stay running with nobody on it.
                # A job another owner took is left alone (release_to_queue checks the owner).
                queue.release_to_queue(
                    self.services.sessions, job.id, self.id, error or "interrupted"
                )
                log.warning("job %s interrupted: %s", job.id, error)
            elif status != queue.SUCCEEDED:
                ctx.flush_logs()
                self.end(job.id, status, error)
            else:
                log.info("job %s succeeded", job.id)
        finally:
            try:
                ctx.flush_logs()
            except Exception:  # noqa: BLE001
                log.exception("could not write the log of job %s", job.id)
            shutil.rmtree(workdir, ignore_errors=True)
            self._ctx = None
