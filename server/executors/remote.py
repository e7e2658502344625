"""A job inside a Ray task: its context on the worker, and how its outputs come back.

:func:`run_job_task` is the body of every Ray task the Ray executor submits. It needs no
database and no shared disk: it gets the job's rows and files (``server/executors/bundle.py``)
as arguments, checks each file against its checksum, and runs the same job function as the
embedded executor under a :class:`RemoteJobContext`:

- ``ctx.session()`` reads the rows from an in-memory snapshot database, ``ctx.store`` is an
  artifact store of the shipped files in the task's temporary folder;
- progress and log lines go to the executor's channel actor on the API node, whose answer
  says whether the job was cancelled (so a cancel reaches the task at its next progress
  report, within an epoch or a joint round);
- ``ctx.complete(register)`` keeps ``register`` for the API node. When the job function
  returns, :func:`pack_registration` serialises it (with cloudpickle, as Ray serialises every
  task) and collects the files it refers to in the task's folder; the context and the local
  store are replaced by stand-ins. The API node writes those files to its own scratch folder,
  :func:`restore_registration` rebuilds ``register`` with its paths pointing there and with
  the API's artifact store, and the executor runs it in the same transaction that marks the
  job succeeded. The payload comes only from this service's own tasks, which the executor
  started; it is never user data and never stored.
"""

from __future__ import annotations

import contextvars
import hashlib
import io
import logging
import os
import pickle
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

from ray import cloudpickle

from server.artifacts import ArtifactStore
from server.db.session import session_scope
from server.executors.base import run_job_function
from server.executors.bundle import open_snapshot
from server.jobs import queue
from server.jobs.context import JobContext, Register

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


@dataclass
class JobSpec:
    job_id: int
    kind: str
    params: dict[str, Any]
    attempt: int
    token: str  # names this attempt on the channel
    run: Callable[[JobContext], None]
    settings: JobSettings


@dataclass
class TaskOutcome:
    status: str  # succeeded, failed, cancelled or interrupted
    error: str | None
    node: str
    registration: bytes | None = None
    files: dict[str, bytes] = field(default_factory=dict)  # path under the task folder -> bytes
    logs: list[tuple[str, str]] = field(default_factory=list)


class RemoteJobContext(JobContext):
    """A job's context inside a Ray task (see the module's docstring)."""

    def __init__(self, spec: JobSpec, root: Path, store: ArtifactStore, sessions, channel: Any):
        super().__init__(spec.job_id, spec.kind, spec.params, root / "work")
        self.spec = spec
        self.root = root
        self._store = store
        self._sessions = sessions
        self.channel = channel
        self.registration: Register | None = None

    @property
    def settings(self) -> JobSettings:
        return self.spec.settings

    @property
    def store(self) -> ArtifactStore:
        return self._store

    def session(self):
        return session_scope(self._sessions)

    def _send(self, progress: float | None, message: str | None, logs: list[tuple[str, str]]) -> None:
        import ray

        deadline = time.monotonic() + CHANNEL_TIMEOUT_S
        while True:
            try:
                state = ray.get(self.channel.report.remote(self.spec.token, progress, message, logs), timeout=CHANNEL_TIMEOUT_S)
                break
            except ray.exceptions.ActorUnavailableError as e:
                # Unavailable is not dead: a loaded node can miss a connection for a moment.
                # Ask again until the deadline (a repeated report may repeat log lines).
                if time.monotonic() > deadline:
                    log.warning("job %s: the API node's channel has not answered for %.0f s (%s); stopping", self.job_id, CHANNEL_TIMEOUT_S, type(e).__name__)
                    self.lost.set()
                    return
                time.sleep(1.0)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError) as e:
                log.warning("job %s: the API node's channel does not answer (%s); stopping", self.job_id, type(e).__name__)
                self.lost.set()
                return
        if state == CANCEL:
            self.cancel_requested.set()
        elif state == LOST:
            self.lost.set()

    def _register(self, register: Register) -> dict[str, Any]:
        self.registration = register
        return {}

    def pending_logs(self) -> list[tuple[str, str]]:
        with self._lock:
            pending, self._pending_logs = self._pending_logs, []
        return pending


# -- the registration, from the task to the API node ---------------------------------------

_RESTORE: contextvars.ContextVar[_Restore] = contextvars.ContextVar("csa_restore_registration")


@dataclass
class _Restore:
    folder: Path
    stand_ins: dict[str, Any]


def _under(folder: Path, relative: str) -> Path:
    rel = PurePath(relative)
    if rel.is_absolute() or ".." in rel.parts:
        raise ValueError(f"a task path must be relative and stay inside the task folder: {relative!r}")
    return folder / rel


def _task_path(relative: str) -> Path:
    """A path of the task's folder, on the API node: the same place under its scratch folder."""
    return _under(_RESTORE.get().folder, relative)


def _stand_in(name: str) -> Any:
    return _RESTORE.get().stand_ins[name]


class _RegistrationPickler(cloudpickle.Pickler):
    """cloudpickle, with paths under the task folder made relative (the files they name are
    collected in :attr:`files`) and named objects replaced by stand-ins."""

    def __init__(self, file: io.BytesIO, root: Path, stand_ins: dict[int, str]):
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.root = root.resolve()
        self.stand_ins = stand_ins
        self.files: set[str] = set()

    def reducer_override(self, obj: Any) -> Any:
        name = self.stand_ins.get(id(obj))
        if name is not None:
            return _stand_in, (name,)
        if isinstance(obj, PurePath) and Path(obj).is_absolute():
            path = Path(obj).resolve()
            if path.is_relative_to(self.root):
                relative = path.relative_to(self.root).as_posix()
                if path.is_file():
                    self.files.add(relative)
                return _task_path, (relative,)
        return super().reducer_override(obj)


def pack_registration(ctx: RemoteJobContext) -> tuple[bytes, dict[str, bytes]]:
    """The job's ``register`` as bytes, and the task-folder files it refers to."""
    assert ctx.registration is not None
    buf = io.BytesIO()
    pickler = _RegistrationPickler(buf, ctx.root, {id(ctx): "context", id(ctx.store): "store"})
    pickler.dump(ctx.registration)
    files = {rel: (ctx.root / rel).read_bytes() for rel in sorted(pickler.files)}
    return buf.getvalue(), files


@dataclass
class RegistrationContext:
    """What ``register`` sees as ``ctx`` on the API node."""

    job_id: int
    kind: str
    params: dict[str, Any]
    workdir: Path
    store: ArtifactStore
    settings: Any
    sessions: Any

    def session(self):
        return session_scope(self.sessions)


def restore_registration(outcome: TaskOutcome, folder: Path, context: RegistrationContext) -> Register:
    """Write the outcome's files under ``folder`` and rebuild its ``register``."""
    assert outcome.registration is not None
    for relative, data in outcome.files.items():
        dest = _under(folder, relative)
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(data)
    token = _RESTORE.set(_Restore(folder, {"context": context, "store": context.store}))
    try:
        return pickle.loads(outcome.registration)
    finally:
        _RESTORE.reset(token)


# -- the task ------------------------------------------------------------------------------


def _unpack_files(store: ArtifactStore, files: dict[str, Any]) -> None:
    """Fetch the shipped files from the object store into ``store``, each checked against its
    checksum (a file that changed on the way fails the job instead of poisoning it)."""
    import ray

    shas = sorted(files)
    for i in range(0, len(shas), _FETCH_CHUNK):
        chunk = shas[i : i + _FETCH_CHUNK]
        for sha, data in zip(chunk, ray.get([files[s] for s in chunk]), strict=True):
            if hashlib.sha256(data).hexdigest() != sha:
                raise OSError(f"artifact {sha[:12]} arrived with a different checksum")
            dest = store.path_of(sha)
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(data)


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


def run_job_task(spec: JobSpec, rows: dict[str, list[dict[str, Any]]], files: dict[str, Any], channel: Any) -> TaskOutcome:
    """The body of a Ray task: run one attempt of a job and hand back its outcome."""
    import ray

    node = ray.get_runtime_context().get_node_id()
    for folder in remove_dead_task_folders():
        log.warning("removed %s, the folder of a task whose process was killed", folder)
    root = task_folder(spec.job_id)
    try:
        store = ArtifactStore(root / "inputs")
        ctx = RemoteJobContext(spec, root, store, open_snapshot(rows), channel)
        ctx.workdir.mkdir()
        import torch

        logging.getLogger("csa_core").setLevel(logging.INFO)  # the core's progress lines reach the job's log
        torch.set_num_threads(spec.settings.torch_threads or max(1, int(ray.get_runtime_context().get_assigned_resources().get("CPU", 1))))
        where = f"running on Ray node {node[:12]} (pid {os.getpid()}, attempt {spec.attempt})"

        def job(ctx: JobContext) -> None:
            ctx.log(where)
            ctx.progress(0.0, where, force=True)  # a job cancelled while it waited stops here
            _unpack_files(store, files)
            ctx.log(f"received {len(files)} input file(s) and {sum(len(r) for r in rows.values())} database row(s)")
            spec.run(ctx)

        status, error = run_job_function(ctx, job)
        outcome = TaskOutcome(status, error, node)
        if status == "succeeded":
            try:
                outcome.registration, outcome.files = pack_registration(ctx)
            except Exception as e:  # noqa: BLE001 - a registration that cannot travel fails the job
                outcome.status, outcome.error = "failed", f"could not send the registration to the API node: {type(e).__name__}: {e}"
        outcome.logs = ctx.pending_logs()
        return outcome
    finally:
        shutil.rmtree(root, ignore_errors=True)
