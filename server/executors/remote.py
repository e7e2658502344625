"""A job inside a Ray task: its context on the worker, and how its Inputs and Outputs travel.

:func:`run_job_task` is the body of every Ray task the Ray executor submits. It needs no
database and no shared disk: the API node ran the job's ``gather`` and sends its Inputs (a
plain dataclass, ``server/jobs/phases.py``) with the bytes of every file they name
(:func:`input_files`). The task checks each file against its checksum, points the Inputs at
its own copies, and runs the kind's ``compute`` (imported by name, :class:`JobSpec`) under a
:class:`RemoteJobContext`, whose progress and log lines go to the executor's channel actor
on the API node; the channel's answer says whether the job was cancelled, so a cancel
reaches the task at its next progress report (within an epoch or a joint round).

The task returns the Outputs (a plain dataclass) with the files they name, as paths relative
to the job's folder (:func:`pack_outputs`). The API node writes those files into its own
scratch folder and points the Outputs there (:func:`unpack_outputs`), and the executor runs
the kind's ``register`` in the transaction that marks the job succeeded. Between the API node
and a job's task only plain values and files travel: no pickled closure, and no registration
function (``register`` runs on the API node, from the API's own job kinds).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

from server.executors.base import run_job_function
from server.jobs import queue
from server.jobs.context import JobContext
from server.jobs.phases import (
    FileRef,
    compute_outputs,
    existing,
    leaves,
    replace_leaves,
    resolve_function,
)

log = logging.getLogger(__name__)

RUN, CANCEL, LOST = "run", "cancel", "lost"  # the channel's answers to a report
TASK_FOLDER_PREFIX = "csa-job-"  # a task's folder on its node: csa-job-<job id>-<random>
TASK_OWNER_FILE = "owner"  # in a task's folder: "<hostname> <pid>" of the process that made it
CHANNEL_TIMEOUT_S = 60.0
_FETCH_CHUNK = 64  # shipped files fetched from the object store at a time


@dataclass(frozen=True)
class JobSettings:
    """What a job reads from ``ctx.settings`` (never the API keys or the database URL)."""

    device: str = "auto"
    torch_threads: int | None = None
    job_log_lines: int = 2000


@dataclass(frozen=True)
class JobSpec:
    job_id: int
    kind: str
    attempt: int
    token: str  # names this attempt on the channel
    compute: str  # the kind's compute, as server.jobs.phases.function_path names it
    settings: JobSettings


@dataclass
class TaskOutcome:
    status: str  # succeeded, failed, cancelled or interrupted
    error: str | None
    node: str
    outputs: Any = None  # the kind's Outputs, their paths relative to the job's folder
    files: dict[str, tuple[str, bytes]] = field(default_factory=dict)  # path -> (sha256, bytes)
    logs: list[tuple[str, str]] = field(default_factory=list)


class RemoteJobContext(JobContext):
    """A job's context inside a Ray task (see the module's docstring)."""

    def __init__(self, spec: JobSpec, workdir: Path, channel: Any):
        super().__init__(spec.job_id, spec.kind, workdir)
        self.spec = spec
        self.channel = channel

    @property
    def settings(self) -> JobSettings:
        return self.spec.settings

    def _send(
        self, progress: float | None, message: str | None, logs: list[tuple[str, str]]
    ) -> None:
        import ray

        deadline = time.monotonic() + CHANNEL_TIMEOUT_S
        while True:
            try:
                state = ray.get(
                    self.channel.report.remote(self.spec.token, progress, message, logs),
                    timeout=CHANNEL_TIMEOUT_S,
                )
                break
            except ray.exceptions.ActorUnavailableError as e:
                # Unavailable is not dead: a loaded node can miss a connection for a moment.
                # Ask again until the deadline (a repeated report may repeat log lines).
                if time.monotonic() > deadline:
                    log.warning(
                        "job %s: the API node's channel has not answered for %.0f s (%s); stopping",
                        self.job_id,
                        CHANNEL_TIMEOUT_S,
                        type(e).__name__,
                    )
                    self.lost.set()
                    return
                time.sleep(1.0)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError) as e:
                log.warning(
                    "job %s: the API node's channel does not answer (%s); stopping",
                    self.job_id,
                    type(e).__name__,
                )
                self.lost.set()
                return
        if state == CANCEL:
            self.cancel_requested.set()
        elif state == LOST:
            self.lost.set()

    def pending_logs(self) -> list[tuple[str, str]]:
        with self._lock:
            pending, self._pending_logs = self._pending_logs, []
        return pending


# -- Inputs, from the API node to the task ---------------------------------------------------


def input_files(inputs: Any) -> dict[str, Path]:
    """The files an Inputs names (checksum -> path on the API node), each once."""
    return {ref.sha256: Path(ref.path) for ref in leaves(inputs, FileRef)}


def read_input_files(inputs: Any) -> Iterator[tuple[str, bytes]]:
    """(checksum, bytes) of every file an Inputs names, one file at a time
    (``ArtifactMissing`` for a file that is not there)."""
    for sha, path in sorted(input_files(inputs).items()):
        yield sha, existing(FileRef(path, sha)).read_bytes()


def _unpack_files(folder: Path, files: dict[str, Any]) -> dict[str, Path]:
    """Fetch the shipped files from the object store into ``folder``, each checked against its
    checksum (a file that changed on the way fails the job instead of poisoning it); returns
    checksum -> path."""
    import ray

    folder.mkdir(parents=True, exist_ok=True)
    local: dict[str, Path] = {}
    shas = sorted(files)
    for i in range(0, len(shas), _FETCH_CHUNK):
        chunk = shas[i : i + _FETCH_CHUNK]
        for sha, data in zip(chunk, ray.get([files[s] for s in chunk]), strict=True):
            if hashlib.sha256(data).hexdigest() != sha:
                raise OSError(f"artifact {sha[:12]} arrived with a different checksum")
            local[sha] = folder / sha
            local[sha].write_bytes(data)
    return local


def localize_inputs(inputs: Any, local: dict[str, Path]) -> Any:
    """``inputs`` with each file pointing at the task's copy (checksum -> path)."""

    def moved(ref: FileRef) -> FileRef:
        return dataclasses.replace(ref, path=local[ref.sha256])

    return replace_leaves(inputs, FileRef, moved)


# -- Outputs, from the task to the API node --------------------------------------------------


def _under(folder: Path, relative: str) -> Path:
    rel = PurePath(relative)
    if rel.is_absolute() or ".." in rel.parts:
        raise ValueError(
            f"a task path must be relative and stay inside the task folder: {relative!r}"
        )
    return folder / rel


def pack_outputs(outputs: Any, workdir: Path) -> tuple[Any, dict[str, tuple[str, bytes]]]:
    """``outputs`` with its paths made relative to ``workdir``, and the files they name
    (relative path -> (sha256, bytes)). Every path must name a file under ``workdir``
    (``server.jobs.phases.compute_outputs`` checked it)."""
    root = workdir.resolve()
    files: dict[str, tuple[str, bytes]] = {}

    def relative(path: PurePath) -> Path:
        rel = Path(path).resolve().relative_to(root).as_posix()
        if rel not in files:
            data = Path(path).read_bytes()
            files[rel] = (hashlib.sha256(data).hexdigest(), data)
        return Path(rel)

    return replace_leaves(outputs, PurePath, relative), files


def unpack_outputs(outputs: Any, files: dict[str, tuple[str, bytes]], folder: Path) -> Any:
    """On the API node: write a task's files under ``folder`` (each checked against its
    checksum) and return its ``outputs`` with their paths pointing there."""
    for relative, (sha, data) in files.items():
        dest = _under(folder, relative)
        if hashlib.sha256(data).hexdigest() != sha:
            raise OSError(f"output {relative} arrived with a different checksum")
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(data)

    def absolute(path: PurePath) -> Path:
        relative = PurePath(path).as_posix()
        if relative not in files:
            raise ValueError(f"the outputs name {relative!r}, which the task did not send")
        return _under(folder, relative)

    return replace_leaves(outputs, PurePath, absolute)


# -- the task ------------------------------------------------------------------------------


def task_folder(job_id: int, parent: Path | None = None) -> Path:
    """A new folder for one attempt of a job (``csa-job-<id>-...`` in the node's temporary
    folder), with a file naming its host and process, so that a later task can tell when the
    attempt was killed (:func:`remove_dead_task_folders`)."""
    root = Path(tempfile.mkdtemp(prefix=f"{TASK_FOLDER_PREFIX}{job_id}-", dir=parent))
    (root / TASK_OWNER_FILE).write_text(f"{socket.gethostname()} {os.getpid()}\n")
    return root


def remove_dead_task_folders(parent: Path | None = None) -> list[Path]:
    """Delete the task folders under ``parent`` (the temporary folder) whose process, on this
    host, no longer exists: those of attempts killed with their worker process or node, which
    never reached their own clean-up. Folders of other hosts (a shared disk) and of live
    processes are left alone; returns the folders removed."""
    parent = Path(parent or tempfile.gettempdir())
    removed = []
    for folder in parent.glob(f"{TASK_FOLDER_PREFIX}*"):
        try:
            host, pid = (folder / TASK_OWNER_FILE).read_text().split()
            dead = host == socket.gethostname() and not queue.pid_alive(int(pid))
        except (OSError, ValueError):
            continue  # not a task folder, or one being made right now
        if dead:
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


def run_job_task(spec: JobSpec, inputs: Any, files: dict[str, Any], channel: Any) -> TaskOutcome:
    """The body of a Ray task: run the compute phase of one attempt of a job and hand back its
    outcome."""
    import ray

    node = ray.get_runtime_context().get_node_id()
    for folder in remove_dead_task_folders():
        log.warning("removed %s, the folder of a task whose process was killed", folder)
    root = task_folder(spec.job_id)
    try:
        ctx = RemoteJobContext(spec, root / "work", channel)
        ctx.workdir.mkdir()
        import torch

        logging.getLogger("csa_core").setLevel(
            logging.INFO
        )  # the core's progress lines reach the job's log
        torch.set_num_threads(
            spec.settings.torch_threads
            or max(1, int(ray.get_runtime_context().get_assigned_resources().get("CPU", 1)))
        )
        where = f"running on Ray node {node[:12]} (pid {os.getpid()}, attempt {spec.attempt})"
        computed: list[Any] = []

        def job(ctx: JobContext) -> None:
            ctx.log(where)
            ctx.progress(0.0, where, force=True)  # a job cancelled while it waited stops here
            local = _unpack_files(root / "inputs", files)
            ctx.log(f"received {len(files)} input file(s)")
            compute = resolve_function(spec.compute)
            mine = localize_inputs(inputs, local)
            computed.append(compute_outputs(compute, mine, ctx.workdir, ctx))

        status, error = run_job_function(ctx, job)
        outcome = TaskOutcome(status, error, node)
        if status == queue.SUCCEEDED:
            try:
                outcome.outputs, outcome.files = pack_outputs(computed[0], ctx.workdir)
            except Exception as e:  # noqa: BLE001 - outputs that cannot travel fail the job
                outcome.status, outcome.error = (
                    queue.FAILED,
                    f"could not send the outputs to the API node: {type(e).__name__}: {e}",
                )
        outcome.logs = ctx.pending_logs()
        return outcome
    finally:
        shutil.rmtree(root, ignore_errors=True)
