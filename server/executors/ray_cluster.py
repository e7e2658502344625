"""The Ray executor (``CSA_EXECUTOR=ray``): jobs run as Ray tasks on a cluster, while the
database on the API node stays the source of truth.

The API process is the cluster's driver. Its dispatcher thread

- claims queued jobs in the database as the embedded executor does (oldest first; jobs of one
  model lineage one at a time, in order, through ``lineage_locks``), as many as the cluster
  has slots for (GPUs when it has any, else CPUs / ``CSA_RAY_CPUS_PER_JOB``; or
  ``CSA_RAY_MAX_RUNNING_JOBS``), so NeRF fits of different scenes run in parallel;
- runs each job's ``gather`` (``server/jobs/phases.py``) and submits one task
  (:func:`server.executors.remote.run_job_task`) with its Inputs and the files they name and
  the resources its kind needs: one GPU for fits, adaptation and pre-training when the
  cluster has GPUs, CPUs otherwise; the task runs the kind's ``compute``;
- drains the channel actor (:class:`JobChannel`, on the API's node) into the database:
  progress, status lines and log lines; a client's cancel goes back through the same channel
  and reaches the task at its next progress report; a task still running
  ``CSA_RAY_CANCEL_GRACE_SECONDS`` after the cancel is killed (``ray.cancel(force=True)``);
- on a task's outcome, writes the files its Outputs name into a scratch folder and runs the
  kind's ``register`` on them in the transaction that marks the job succeeded
  (``queue.finish``), which stores them in the artifact store;
- when a task's worker process or node dies (``WorkerCrashedError``, ``NodeDiedError``, ...),
  re-queues the job for another attempt, or fails it with the reason after
  ``CSA_MAX_ATTEMPTS`` attempts (``queue.attempt_lost``). Ray's own retries are off
  (``max_retries=0``) so that every attempt is visible in the job's row and log.

When the API process stops, running jobs are handed back to the queue and their tasks
cancelled; when it is killed, Ray ends the tasks of the dead driver and the next API process
re-queues the jobs (``queue.recover_stale_jobs``), so no job stays ``running``.

Ray is imported only here and in ``server/executors/remote.py``, never on the embedded path.
"""

from __future__ import annotations

import logging
import shutil
import signal
import threading
import time
import traceback
import uuid
from dataclasses import dataclass
from typing import Any

from server.db.session import session_scope
from server.executors.base import INTERRUPTED, Executor, failure, unexpected
from server.executors.remote import (
    CANCEL,
    CHANNEL_TIMEOUT_S,
    LOST,
    RUN,
    JobSettings,
    JobSpec,
    TaskOutcome,
    read_input_files,
    run_job_task,
    unpack_outputs,
)
from server.jobs import queue
from server.jobs.kinds import KINDS, JobKind, runnable_kinds
from server.jobs.phases import ApiNode, function_path, gather_inputs

log = logging.getLogger(__name__)

_RESOURCES_EVERY = 1.0  # seconds between reads of the cluster's resources (nodes come and go)


class JobChannel:
    """The Ray actor between running tasks and the dispatcher. A task reports progress and log
    lines under its attempt's token and learns whether to go on (:data:`RUN`), stop because
    the job was cancelled (:data:`CANCEL`) or stop because the attempt no longer counts
    (:data:`LOST`); the dispatcher drains the reports and signals cancels."""

    def __init__(self) -> None:
        self._events: dict[str, dict[str, Any]] = {}
        self._cancel: set[str] = set()
        self._lost: set[str] = set()

    def report(
        self, token: str, progress: float | None, message: str | None, logs: list[tuple[str, str]]
    ) -> str:
        ev = self._events.setdefault(token, {"progress": None, "message": None, "logs": []})
        if progress is not None:
            ev["progress"] = progress
        if message is not None:
            ev["message"] = message
        ev["logs"].extend(logs)
        return LOST if token in self._lost else CANCEL if token in self._cancel else RUN

    def drain(self) -> dict[str, dict[str, Any]]:
        events, self._events = self._events, {}
        return events

    def signal(self, cancel: list[str], lost: list[str]) -> None:
        self._cancel.update(cancel)
        self._lost.update(lost)

    def forget(self, tokens: list[str]) -> None:
        self._cancel.difference_update(tokens)
        self._lost.difference_update(tokens)


@dataclass
class _Attempt:
    job_id: int
    kind: str
    token: str
    ref: Any  # the task's ObjectRef
    submitted: float  # time.monotonic()
    cancel_since: float | None = None
    killed: bool = False  # ray.cancel(force=True) was sent
    lost: bool = False  # the database says another owner has the job now


def task_device(configured: str, num_gpus: float) -> str:
    """The torch device of a Ray task: the configured one where the task reserved a GPU, else
    the CPU (newer Ray no longer hides a node's GPUs from tasks that reserved none, and such a
    task would otherwise share a GPU that another job holds)."""
    return configured if num_gpus >= 1 else "cpu"


def lost_worker_reason(error: BaseException) -> str:
    """Why an attempt was lost with its worker, for the job's status line and log: Ray's error
    type and the whole sentences of its message that fit in 300 characters (its messages run
    to several sentences of advice; the first says what happened)."""
    return f"its Ray worker was lost ({type(error).__name__}: {queue.brief(str(error), 300)})"


class RayExecutor(Executor):
    mode = "ray"

    def __init__(self, services):
        super().__init__(services)
        self._attempts: dict[str, _Attempt] = {}
        self._lock = threading.Lock()
        self._leases: tuple[float, set[int], set[int]] | None = None  # (when, owned, cancelled)
        self._resources: dict[str, float] = {}
        self._resources_at = -_RESOURCES_EVERY
        self._last_recover = -1e9
        self._owns_ray = False
        self._channel: Any = None
        self._channel_unavailable_since: float | None = None
        self._task: Any = None

    # -- connection ----------------------------------------------------------------------

    def start(self) -> None:
        """Connect to the cluster now (a wrong address fails the API's start-up with the
        reason), then dispatch from a thread."""
        self.connect()
        super().start()

    def connect(self) -> None:
        import ray

        address = self.settings.ray_address
        if not ray.is_initialized():
            # ray.init replaces the SIGTERM handler of the main thread; keep the server's, so
            # that stopping the API still hands running jobs back.
            previous = (
                signal.getsignal(signal.SIGTERM)
                if threading.current_thread() is threading.main_thread()
                else None
            )
            try:
                if address == "local":
                    ray.init(
                        num_cpus=self.settings.ray_num_cpus,
                        include_dashboard=False,
                        namespace="csa",
                    )
                else:
                    ray.init(address=address, namespace="csa")
            except Exception as e:
                raise RuntimeError(
                    f"CSA_RAY_ADDRESS={address!r}: cannot connect to a Ray cluster: "
                    f"{type(e).__name__}: {e}"
                ) from e
            finally:
                if previous is not None:
                    signal.signal(signal.SIGTERM, previous)
            self._owns_ray = True
        self._task = ray.remote(run_job_task)
        self._channel = self._new_channel()
        log.info("Ray executor %s connected (%s): %s", self.id, address, ray.cluster_resources())

    def _new_channel(self) -> Any:
        """The channel actor, on the API's own node (it needs no CPU), so that losing a worker
        node never loses the channel."""
        import ray
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        # Hard affinity: a soft one moves the actor to another node whenever the API's node
        # looks busy (a task holding its CPUs), and then losing that node loses the channel.
        near_api = NodeAffinitySchedulingStrategy(
            node_id=ray.get_runtime_context().get_node_id(), soft=False
        )
        channel = (
            ray.remote(JobChannel)
            .options(num_cpus=0, scheduling_strategy=near_api, max_restarts=0)
            .remote()
        )
        ray.get(channel.drain.remote(), timeout=120)  # it answers before any task reports to it
        return channel

    def close(self) -> None:
        """Hand running jobs back to the queue and stop their tasks, then disconnect."""
        import ray

        for a in list(self._attempts.values()):
            queue.release_to_queue(
                self.services.sessions, a.job_id, self.id, "the API is shutting down"
            )
            try:
                ray.cancel(a.ref, force=True)
            except Exception:  # noqa: BLE001 - the task may have ended meanwhile
                log.debug("could not cancel the task of job %s", a.job_id, exc_info=True)
        self._attempts.clear()
        if self._channel is not None:
            try:
                ray.kill(self._channel)
            except Exception:  # noqa: BLE001
                log.debug("channel already gone", exc_info=True)
        if self._owns_ray:
            ray.shutdown()

    # -- the loop ------------------------------------------------------------------------

    def on_leases(self, owned: set[int], cancel: set[int], since: float) -> None:
        with self._lock:
            self._leases = (since, owned, cancel)

    def step(self) -> bool:
        import ray

        self._drain()
        self._apply_leases()
        self._collect()
        now = time.monotonic()
        if now - self._last_recover >= self.settings.heartbeat_seconds:
            self._last_recover = now
            self.recover()
        self._submit_more()
        refs = [a.ref for a in self._attempts.values()]
        if refs:
            ray.wait(refs, num_returns=1, timeout=self.settings.worker_poll_seconds)
        else:
            self.stopping.wait(self.settings.worker_poll_seconds)
        return True

    def _drain(self) -> None:
        """Write what the tasks reported into the database; pass cancels back to them."""
        import ray

        try:
            events = ray.get(self._channel.drain.remote(), timeout=60)
            self._channel_unavailable_since = None
        except ray.exceptions.ActorUnavailableError as e:
            # Not dead (that is ActorDiedError): a loaded node can drop a connection for a
            # moment. Tasks wait as long for it (remote.CHANNEL_TIMEOUT_S) before they stop.
            now = time.monotonic()
            if self._channel_unavailable_since is None:
                self._channel_unavailable_since = now
            if now - self._channel_unavailable_since < CHANNEL_TIMEOUT_S:
                log.warning("the job channel did not answer (%s); asking again", type(e).__name__)
                return
            log.warning(
                "the job channel has not answered for %.0f s; starting a new one", CHANNEL_TIMEOUT_S
            )
            self._channel_unavailable_since = None
            self._channel = self._new_channel()
            return
        except ray.exceptions.RayActorError as e:
            # Running tasks hold the old channel: their next report fails, they stop, and
            # their jobs go back to the queue as lost attempts.
            log.warning("the job channel died (%s); starting a new one", type(e).__name__)
            self._channel = self._new_channel()
            return
        cancel: list[str] = []
        for token, ev in events.items():
            a = self._attempts.get(token)
            if a is None or a.lost:
                continue  # an attempt that already ended (or a stale one)
            try:
                cancelled = queue.report(
                    self.services.sessions,
                    a.job_id,
                    self.id,
                    ev["progress"],
                    ev["message"],
                    ev["logs"],
                    self.settings.job_log_lines,
                )
            except queue.LostJob:
                self._lose(a)
                continue
            if cancelled and a.cancel_since is None:
                a.cancel_since = time.monotonic()
                cancel.append(token)
        if cancel:
            self._channel.signal.remote(cancel, [])

    def _lose(self, a: _Attempt) -> None:
        """The database gave the job to someone else (recovered after a lease expired): stop the
        task."""
        import ray

        a.lost = True
        log.warning("job %s is no longer owned by %s; stopping its task", a.job_id, self.id)
        self._channel.signal.remote([], [a.token])
        ray.cancel(a.ref, force=True)

    def _apply_leases(self) -> None:
        import ray

        with self._lock:
            leases, self._leases = self._leases, None
        now = time.monotonic()
        if leases is not None:
            seen_at, owned, cancelled = leases
            cancel: list[str] = []
            for a in self._attempts.values():
                if a.lost or a.submitted > seen_at:
                    continue
                if a.job_id not in owned:
                    self._lose(a)
                elif a.job_id in cancelled and a.cancel_since is None:
                    a.cancel_since = now
                    cancel.append(a.token)
            if cancel:
                self._channel.signal.remote(cancel, [])
        grace = self.settings.ray_cancel_grace_seconds
        for a in self._attempts.values():
            if a.cancel_since is not None and not a.killed and now - a.cancel_since > grace:
                a.killed = True
                log.warning(
                    "job %s did not stop within %.0f s of its cancel; killing its task",
                    a.job_id,
                    grace,
                )
                ray.cancel(a.ref, force=True)

    def _collect(self) -> None:
        import ray

        if not self._attempts:
            return
        by_ref = {a.ref: a for a in self._attempts.values()}
        ready, _ = ray.wait(list(by_ref), num_returns=len(by_ref), timeout=0)
        if not ready:
            return
        self._drain()  # what a task reported before it ended goes in before its outcome
        ended = [by_ref[r] for r in ready]
        for a in ended:
            del self._attempts[a.token]
            try:
                self._settle(a)
            except Exception:  # noqa: BLE001 - one bad outcome must not stop the others
                log.exception("could not settle job %s", a.job_id)
        self._channel.forget.remote([a.token for a in ended])

    def _settle(self, a: _Attempt) -> None:
        import ray
        from ray.exceptions import RayError, RayTaskError, TaskCancelledError

        sessions = self.services.sessions
        try:
            outcome: TaskOutcome = ray.get(a.ref)
        except TaskCancelledError:
            if a.lost:
                return
            if a.cancel_since is not None:
                self.end(
                    a.job_id,
                    queue.CANCELLED,
                    "cancelled by request (its task was stopped "
                    f"{self.settings.ray_cancel_grace_seconds:.0f} s after the cancel)",
                )
            else:
                queue.attempt_lost(
                    sessions,
                    a.job_id,
                    self.id,
                    "its Ray task was cancelled",
                    self.settings.max_attempts,
                )
            return
        except RayTaskError as e:
            cause = e.cause if e.cause is not None else e
            self._log(a.job_id, [("ERROR", str(e)[-4000:])])
            self.end(
                a.job_id, queue.FAILED, f"the Ray task failed: {type(cause).__name__}: {cause}"
            )
            return
        except RayError as e:
            if a.lost:
                return
            reason = lost_worker_reason(e)
            status = queue.attempt_lost(
                sessions, a.job_id, self.id, reason, self.settings.max_attempts
            )
            log.warning("job %s: %s -> %s", a.job_id, reason, status)
            return
        if a.lost:
            return
        self._log(a.job_id, outcome.logs)
        if outcome.status == INTERRUPTED:
            queue.attempt_lost(
                sessions,
                a.job_id,
                self.id,
                f"its task stopped: {outcome.error}",
                self.settings.max_attempts,
            )
        elif outcome.status != queue.SUCCEEDED:
            self.end(a.job_id, outcome.status, outcome.error)
        else:
            self._register_outputs(a, outcome)

    def _register_outputs(self, a: _Attempt, outcome: TaskOutcome) -> None:
        """Write the files of the task's Outputs and run the kind's ``register`` on them, in
        the transaction that ends the job."""
        folder = self.settings.resolved_work_dir / self.scratch_folder(a.job_id)
        try:
            kind, node = KINDS[a.kind], ApiNode(a.job_id, self.services.store)
            outputs = unpack_outputs(outcome.outputs, outcome.files, folder)
            queue.finish(
                self.services.sessions,
                a.job_id,
                self.id,
                queue.SUCCEEDED,
                register=lambda s: kind.register(s, outputs, node),
            )
            log.info("job %s succeeded on node %s", a.job_id, outcome.node[:12])
        except queue.LostJob:
            log.warning(
                "job %s was recovered by another executor before it was registered", a.job_id
            )
        except Exception as e:  # noqa: BLE001 - a registration that fails fails the job, not the executor
            self._log(a.job_id, [("ERROR", traceback.format_exc(limit=20))])
            self.end(a.job_id, queue.FAILED, f"{type(e).__name__}: {e}")
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _log(self, job_id: int, lines: list[tuple[str, str]]) -> None:
        if not lines:
            return
        try:
            queue.report(
                self.services.sessions,
                job_id,
                self.id,
                logs=lines,
                keep_log_lines=self.settings.job_log_lines,
            )
        except queue.LostJob:
            pass  # the lines are kept; the job has moved on

    # -- submission ----------------------------------------------------------------------

    def _cluster(self) -> dict[str, float]:
        import ray

        now = time.monotonic()
        if now - self._resources_at >= _RESOURCES_EVERY:
            self._resources, self._resources_at = ray.cluster_resources(), now
        return self._resources

    def slots(self) -> int:
        """How many jobs the cluster runs at once."""
        if self.settings.ray_max_running_jobs:
            return self.settings.ray_max_running_jobs
        res = self._cluster()
        gpus, cpus = res.get("GPU", 0.0), res.get("CPU", 0.0)
        return max(1, int(gpus) if gpus >= 1 else int(cpus // self.settings.ray_cpus_per_job))

    def resources(self, kind: JobKind) -> dict[str, float]:
        gpu = kind.gpu and self._cluster().get("GPU", 0.0) >= 1
        return {"num_cpus": self.settings.ray_cpus_per_job, "num_gpus": 1 if gpu else 0}

    def _submit_more(self) -> None:
        if self.stopping.is_set():
            return
        free = self.slots() - len(self._attempts)
        kinds = runnable_kinds() if free > 0 else set()
        while free > 0 and kinds:
            job = queue.claim_next(
                self.services.sessions, self.id, self.settings.lease_seconds, kinds
            )
            if job is None:
                return
            self._submit(job.id, job.kind, dict(job.params or {}), job.attempts)
            free -= 1

    def _submit(self, job_id: int, kind_name: str, params: dict[str, Any], attempt: int) -> None:
        import ray

        kind = KINDS[kind_name]
        try:
            with session_scope(self.services.sessions) as s:
                inputs = gather_inputs(kind.gather, s, params, ApiNode(job_id, self.services.store))
        except Exception as e:  # noqa: BLE001 - it ends as it would under the embedded executor
            if unexpected(e):
                self._log(job_id, [("ERROR", traceback.format_exc(limit=20))])
            status, error = failure(e)
            self.end(job_id, status, error)
            return
        try:
            compute = function_path(kind.compute)
            files = {sha: ray.put(data) for sha, data in read_input_files(inputs)}
        except Exception as e:  # noqa: BLE001 - e.g. a file missing from the store
            self.end(
                job_id, queue.FAILED, f"could not read the job's inputs: {type(e).__name__}: {e}"
            )
            return
        token = f"{job_id}-{uuid.uuid4().hex[:8]}"
        resources = self.resources(kind)
        device = task_device(self.settings.device, resources["num_gpus"])
        settings = JobSettings(
            device=device,
            torch_threads=self.settings.torch_threads,
            job_log_lines=self.settings.job_log_lines,
        )
        spec = JobSpec(job_id, kind_name, attempt, token, compute, settings)
        # SPREAD: jobs go to different nodes when they can, rather than next to their inputs on
        # the API's node (each job is heavy, and its inputs are small next to its work).
        options = {
            "name": f"csa-{kind_name}-{job_id}",
            "max_retries": 0,
            "scheduling_strategy": "SPREAD",
            **resources,
        }
        ref = self._task.options(**options).remote(spec, inputs, files, self._channel)
        self._attempts[token] = _Attempt(job_id, kind_name, token, ref, time.monotonic())
        wants = ", ".join(f"{k.removeprefix('num_')}={v:g}" for k, v in resources.items())
        self._log(
            job_id,
            [
                (
                    "INFO",
                    f"attempt {attempt}: submitted to the Ray cluster ({wants}) with {len(files)} "
                    "input file(s)",
                )
            ],
        )
        try:
            queue.report(
                self.services.sessions, job_id, self.id, message="waiting for the Ray cluster"
            )
        except queue.LostJob:
            pass
