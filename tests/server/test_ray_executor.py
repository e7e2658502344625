"""Scale-out on Ray, end to end, and the same flow on the embedded executor.

One two-node Ray cluster for the module: two ``ray start`` processes on this machine, one CPU
each (the head, where the API's driver and channel live, and a worker node). A real uvicorn
server with ``CSA_EXECUTOR=ray`` uploads three tiny rooms, pre-trains, fits NeRFs of two
scenes in parallel (one per node), loses the worker node in the middle of a fit (its
processes are killed), and adapts; then the job is retried on the head, and nothing is lost
or half-written. The same flow runs on the embedded executor with SQLite (there the
disruption is an API restart in the middle of a fit). Further tests: cancel reaching a
running task, a task whose worker dies on every attempt, and an API restart while a task runs.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import pytest
from sqlalchemy import func, select

from client import CSAClient
from server import capabilities
from server.db.models import Job, NerfCheckpoint
from server.jobs import queue
from server.jobs.context import JobContext
from server.jobs.kinds import KINDS
from server.jobs.phases import FileRef, check_plain, leaves
from tests.server.conftest import (
    SCENE_SIZE,
    LiveServer,
    ParamsInputs,
    ResultOutputs,
    database_url,
    free_port,
    job_kind,
    start_server,
    test_settings,
)

# Every Ray process of these tests, this one included, stays on the loopback network: the nodes
# listen on 127.0.0.2 (Ray would turn 127.0.0.1 into the machine's network address), and the
# cluster, reachable from this machine only, runs without token authentication.
NODE_IP = "127.0.0.2"
RAY_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
os.environ.update(RAY_ENV)
ray = pytest.importorskip(
    "ray", reason="the Ray executor needs the ray extra (pip install -e '.[ray]')"
)

REPO = Path(__file__).resolve().parents[2]
RAY = Path(sys.executable).with_name("ray")

pytestmark = pytest.mark.skipif(
    not all(capabilities.available(c) for c in ("seg", "nerf", "adapt")),
    reason="needs csa_core.seg, nerf and adapt for real jobs",
)

# Long enough to be killed in the middle, short enough for a test (a few seconds on one core).
FIT = {
    "labels": "predictions",
    "steps": 150,
    "rays_per_step": 256,
    "occupancy_resolution": 32,
    "log2_table_size": 12,
}
LONG_FIT = FIT | {"labels": "ground_truth", "steps": 100_000}
# A lost node is declared dead after 3 missed health checks 0.5 s apart (Ray's default: 15 s).
FAST_FAILURE_DETECTION = {"health_check_period_ms": 500, "health_check_failure_threshold": 3}
FITTING = ("fitting", "NeRF step")  # a fit job's status line while it fits
NODE_LINE = re.compile(r"running on Ray node (\w+) \(pid (\d+), attempt (\d+)\)")


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def kill_session(sid: int) -> None:
    """SIGKILL every process of the session a node was started in (its raylet, its workers,
    and for the head the GCS): what a machine that loses power does to it."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if os.getsid(int(entry.name)) == sid:
                os.kill(int(entry.name), signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            continue


@dataclass
class RayCluster:
    address: str
    logs: Path
    head: subprocess.Popen
    worker: subprocess.Popen | None = None
    all_started: list[subprocess.Popen] = field(default_factory=list)

    @staticmethod
    def env() -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("CSA_", "RAY_"))}
        # The workers import this repository's modules (the test job kinds below among them).
        return env | RAY_ENV | {"PYTHONPATH": str(REPO)}

    @classmethod
    def node(cls, args: list[str], log: Path) -> subprocess.Popen:
        with open(log, "ab") as out:
            return subprocess.Popen(
                [
                    str(RAY),
                    "start",
                    "--block",
                    "--disable-usage-stats",
                    f"--node-ip-address={NODE_IP}",
                    "--num-gpus=0",
                    "--object-store-memory=100000000",
                    *args,
                ],
                env=cls.env(),
                cwd=REPO,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # its own session, so that it can be killed alone
            )

    def start_worker(self) -> None:
        if self.worker is None or self.worker.poll() is not None:
            self.worker = self.node(
                [f"--address={self.address}", "--num-cpus=1"], self.logs / "worker.log"
            )
            self.all_started.append(self.worker)

    def kill_worker(self) -> None:
        assert self.worker is not None
        kill_session(self.worker.pid)
        self.worker.wait(timeout=30)

    def stop(self) -> None:
        for p in self.all_started:
            kill_session(p.pid)
            p.wait(timeout=30)


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory) -> Iterator[RayCluster]:
    logs = tmp_path_factory.mktemp("ray-logs")
    port = free_port()
    head = RayCluster.node(
        [
            "--head",
            f"--port={port}",
            "--num-cpus=1",
            "--include-dashboard=false",
            f"--system-config={json.dumps(FAST_FAILURE_DETECTION)}",
        ],
        logs / "head.log",
    )
    cluster = RayCluster(f"{NODE_IP}:{port}", logs, head, all_started=[head])
    try:

        def listening() -> bool:
            assert head.poll() is None, (logs / "head.log").read_text()[-3000:]
            with socket.socket() as s:
                return s.connect_ex((NODE_IP, port)) == 0

        wait_for(listening, 120, "the Ray head")
        cluster.start_worker()
        yield cluster
    finally:
        cluster.stop()


def ray_settings(cluster: RayCluster) -> dict[str, object]:
    return {"executor": "ray", "ray_address": cluster.address, "ray_cancel_grace_seconds": 20.0}


def wait_for_cpus(n: int) -> None:
    wait_for(
        lambda: ray.cluster_resources().get("CPU", 0) == n, 120, f"{n} CPUs in the Ray cluster"
    )


def warm_up_nodes() -> None:
    """Start a worker process with the job code imported on every node (5-10 s on this
    machine), so that two jobs submitted together really run together: otherwise the job
    on the warm node may be done before the other node's worker has started."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    @ray.remote(num_cpus=1)
    def import_the_jobs() -> int:
        import csa_core.nerf.fit  # noqa: F401
        import csa_core.seg  # noqa: F401
        import server.executors.remote  # noqa: F401

        return os.getpid()

    nodes = [n["NodeID"] for n in ray.nodes() if n["Alive"] and n["Resources"].get("CPU")]
    ray.get(
        [
            import_the_jobs.options(
                scheduling_strategy=NodeAffinitySchedulingStrategy(n, soft=False)
            ).remote()
            for n in nodes
        ],
        timeout=120,
    )


@dataclass
class Rooms:
    pretrain: Path
    a: Path
    b: Path


@pytest.fixture(scope="module")
def rooms(tmp_path_factory) -> Rooms:
    from csa_core.data.synth import synthesize

    folder = tmp_path_factory.mktemp("rooms")
    (pre,) = synthesize(folder, scenes=1, frames=8, size=SCENE_SIZE, family="apartment", seed=1)
    (a,) = synthesize(folder, scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=2)
    (b,) = synthesize(folder, scenes=1, frames=8, size=SCENE_SIZE, family="studio", seed=3)
    return Rooms(pre, a, b)


def attempts_on_nodes(c: CSAClient, job_id: int) -> list[tuple[str, int, int]]:
    """(node, pid, attempt) of each attempt the job's log shows, oldest first."""
    return [
        (m.group(1), int(m.group(2)), int(m.group(3)))
        for line in c.job_log(job_id, tail=500)
        if (m := NODE_LINE.search(line.message))
    ]


def upload_and_pretrain(c: CSAClient, rooms: Rooms) -> None:
    for folder in (rooms.pretrain, rooms.a, rooms.b):
        scene, _ = c.upload_scene_folder(folder)
        assert scene.num_frames == 8
    base = c.wait_job(
        c.pretrain([rooms.pretrain.name], epochs=1, batch_size=4, name="base").id, timeout=180
    )
    assert base.status == "succeeded" and c.model("base").is_current


def check_nothing_lost(live: LiveServer, c: CSAClient, fits: dict[str, int]) -> None:
    """Each scene has exactly the NeRF its fit job registered, every stored file verifies,
    and no scratch folder is left behind."""
    bank = {e.scene: e for e in c.memory().entries}
    assert {scene: bank[scene].job_id for scene in fits} == fits
    services = live.services
    with services.sessions() as s:
        assert s.scalar(select(func.count(NerfCheckpoint.id))) == len(
            fits
        )  # nothing from a lost attempt
        report = services.store.verify(s)
    assert report.ok and report.checked >= 3 * 8 * 3 + 1 + len(fits)
    # A job's scratch folder goes right after the job has ended.
    wait_for(
        lambda: (
            not [
                p
                for p in services.settings.resolved_work_dir.iterdir()
                if p.name.startswith("job-")
            ]
        ),
        30,
        "no scratch folder left",
    )


# The adapted network's val mIoU per set-up: the same inputs, seeds and thread count give the
# same network whichever executor runs the step.
ADAPTED_MIOU: dict[str, float] = {}


def adapt_and_evaluate(c: CSAClient, scene: str, fit_job: int, setup: str) -> None:
    done = c.wait_job(c.adapt(scene, preset="tiny").id, timeout=300)
    new = c.model(done.result["model_id"])
    assert (
        new.name == "base-step1"
        and new.parent_id == c.model("base").id
        and new.adapted_scene == scene
        and new.is_current
    )
    assert 0.0 <= new.metrics["val_miou"] <= 1.0
    entry = c.scene_nerf(scene)
    if done.result["nerf_id"] is not None:
        assert (
            entry.id == done.result["nerf_id"]
            and entry.job_id == done.id
            and entry.labels_source == "adapt:base"
        )
    else:  # the collapse guard kept the step's NeRF out of the bank, and said why
        assert entry.job_id == fit_job and done.result["decisions"]
    scored = c.wait_job(c.evaluate(model=new.name, scenes=[scene]).id, timeout=120)
    (miou,) = scored.result["miou"].values()
    assert miou == pytest.approx(new.metrics["val_miou"])
    ADAPTED_MIOU[setup] = new.metrics["val_miou"]
    assert len(set(ADAPTED_MIOU.values())) == 1, ADAPTED_MIOU


# Ray with PostgreSQL (the scale-out set-up) and the embedded default with SQLite; the Ray-only
# tests below run Ray with SQLite.
SETUPS = [
    pytest.param(("ray", "postgresql"), id="ray-postgresql"),
    pytest.param(("embedded", "sqlite"), id="embedded-sqlite"),
]


@pytest.mark.parametrize("setup", SETUPS)
def test_fits_in_parallel_survive_a_disruption_then_adapt(
    request, setup, rooms: Rooms, tmp_path: Path
) -> None:
    executor, backend = setup
    cluster: RayCluster | None = (
        request.getfixturevalue("ray_cluster") if executor == "ray" else None
    )
    extra = ray_settings(cluster) if cluster is not None else {}
    settings = test_settings(
        tmp_path / "service", database_url=database_url(request, backend), **extra
    )
    live = start_server(settings)
    try:
        c = live.client()
        if cluster is not None:
            cluster.start_worker()
            wait_for_cpus(2)
            warm_up_nodes()
        upload_and_pretrain(c, rooms)
        # On the cluster the two fits must overlap: with the hash-encoding kernel a 150-step fit
        # took a few seconds, and on a loaded 2-core machine one had ended before the other
        # began fitting. Four times the steps leave the overlap slack.
        fit = FIT | {"steps": 4 * FIT["steps"]} if cluster is not None else FIT
        jobs = {
            scene: c.create_job("fit_nerf", scene=scene, **fit).id
            for scene in (rooms.a.name, rooms.b.name)
        }

        if cluster is not None:
            # Both fits run at once, one per node; the one on the worker node loses its node.
            def both_placed():
                placed = {j: attempts_on_nodes(c, j) for j in jobs.values()}
                return placed if all(placed.values()) else None

            placed = wait_for(both_placed, 120, "both fits to start on the cluster")
            assert len({p[0][0] for p in placed.values()}) == 2  # on two nodes
            victim = next(j for j, p in placed.items() if os.getsid(p[0][1]) == cluster.worker.pid)

            def both_fitting() -> bool:
                now = [c.job(j) for j in jobs.values()]
                return all(j.status == "running" and j.message.startswith(FITTING) for j in now)

            wait_for(both_fitting, 120, "both fits to be fitting at the same time")
            cluster.kill_worker()
            assert c.health().status == "ok" and c.job(victim).status in (
                "running",
                "queued",
            )  # the API answers throughout
        else:
            # One process: the disruption is an API restart in the middle of the first fit.
            victim = jobs[rooms.a.name]
            wait_for(
                lambda: c.job(victim).message.startswith(FITTING), 60, "the first fit to be fitting"
            )
            c.close()
            live.stop()
            live = start_server(settings)
            c = live.client()

        done = {scene: c.wait_job(j, timeout=240) for scene, j in jobs.items()}
        assert all(d.status == "succeeded" for d in done.values())
        lines = [line.message for line in c.job_log(victim, tail=500)]
        if cluster is not None:
            assert c.job(victim).attempts == 2 and [j.attempts for j in done.values()].count(1) == 1
            lost = next(
                m
                for m in lines
                if m.startswith("re-queued after attempt 1 of 2: its Ray worker was lost (")
            )
            assert "Error" in lost  # Ray's reason: NodeDiedError or WorkerCrashedError
            (first, second) = attempts_on_nodes(c, victim)
            assert first[0] != second[0] and (first[2], second[2]) == (
                1,
                2,
            )  # retried on the other node
            # The killed attempt's task folder (both nodes share this machine's temporary
            # folder) was removed by the next task here; the second attempt removed its own.
            assert not list(Path(tempfile.gettempdir()).glob(f"csa-job-{victim}-*"))
            # The job's start is its first attempt's (each attempt's start is in the log).
            starts = [
                line.time
                for line in c.job_log(victim, tail=500)
                if line.message.startswith("started on worker")
            ]
            assert len(starts) == 2 and c.job(victim).started_at <= starts[0] < starts[1]
        else:
            assert (
                c.job(victim).attempts == 1
            )  # handed back at shutdown: the attempt does not count
            assert any(m == "re-queued: executor shutting down" for m in lines)
        check_nothing_lost(live, c, {scene: j for scene, j in jobs.items()})
        adapt_and_evaluate(c, rooms.a.name, jobs[rooms.a.name], f"{executor}-{backend}")
        c.close()
    finally:
        live.stop()


# -- every kind through its three phases ------------------------------------------------------

# A fit on predictions: its Inputs name a model version's checkpoint as well as the frames.
TINY_FIT = {
    "labels": "predictions",
    "steps": 60,
    "rays_per_step": 256,
    "occupancy_resolution": 32,
    "log2_table_size": 12,
}
PHASED_KINDS = ("pretrain", "fit_nerf", "evaluate", "adapt")


@dataclass
class Phases:
    """What spies on a kind's ``gather`` and ``register`` (both on the API node) saw: the
    Inputs gathered, the Outputs registered, and whether every file the Outputs named was
    there when they were registered."""

    inputs: list = field(default_factory=list)
    outputs: list = field(default_factory=list)
    files_there: list = field(default_factory=list)


def spy_on_phases(monkeypatch) -> dict[str, Phases]:
    seen = {name: Phases() for name in PHASED_KINDS}
    for name, phases in seen.items():
        kind = KINDS[name]

        def gather(session, params, node, kind=kind, phases=phases):
            inputs = kind.gather(session, params, node)
            phases.inputs.append(inputs)
            return inputs

        def register(session, outputs, node, kind=kind, phases=phases):
            phases.outputs.append(outputs)
            phases.files_there.append(all(Path(p).is_file() for p in leaves(outputs, PurePath)))
            return kind.register(session, outputs, node)

        monkeypatch.setitem(
            KINDS, name, dataclasses.replace(kind, gather=gather, register=register)
        )
    return seen


@pytest.mark.parametrize("executor", ["ray", "embedded"])
def test_every_kind_runs_in_three_phases(
    request, executor: str, rooms: Rooms, tmp_path: Path, monkeypatch
) -> None:
    """Pre-training, a NeRF fit, an evaluation and an adaptation step each gather their Inputs
    and register their Outputs on the API node, and compute where the executor runs them (in a
    Ray task on the cluster): the Inputs name files of the API's artifact store, the Outputs
    reach ``register`` as files in the API's scratch folder, and both are plain values."""
    cluster: RayCluster | None = (
        request.getfixturevalue("ray_cluster") if executor == "ray" else None
    )
    seen = spy_on_phases(monkeypatch)
    live = start_server(
        test_settings(tmp_path / "service", **(ray_settings(cluster) if cluster else {}))
    )
    try:
        c = live.client()
        if cluster is not None:
            cluster.start_worker()
            wait_for_cpus(2)
        for folder in (rooms.pretrain, rooms.a):
            c.upload_scene_folder(folder)
        jobs = {
            "pretrain": c.wait_job(
                c.pretrain([rooms.pretrain.name], epochs=1, batch_size=4, name="base").id,
                timeout=300,
            )
        }
        jobs["fit_nerf"] = c.wait_job(
            c.create_job("fit_nerf", scene=rooms.a.name, **TINY_FIT).id, timeout=300
        )
        jobs["evaluate"] = c.wait_job(
            c.evaluate(model="base", scenes=[rooms.a.name]).id, timeout=300
        )
        jobs["adapt"] = c.wait_job(c.adapt(rooms.a.name, preset="tiny").id, timeout=600)
        assert {name: job.status for name, job in jobs.items()} == dict.fromkeys(
            PHASED_KINDS, "succeeded"
        )

        store = live.services.store.root.resolve()
        work = live.services.settings.resolved_work_dir.resolve()
        for name, job in jobs.items():
            phases = seen[name]
            (inputs,), (outputs,) = phases.inputs, phases.outputs
            for value in (inputs, outputs):
                check_plain(value)
                json.dumps(dataclasses.asdict(value), default=str)
            refs = list(leaves(inputs, FileRef))
            assert refs and all(Path(r.path).resolve().is_relative_to(store) for r in refs), name
            paths = [Path(p) for p in leaves(outputs, PurePath)]
            assert (name == "evaluate") == (
                not paths
            )  # only the scores come back from an evaluation
            assert all(p.resolve().is_relative_to(work) for p in paths) and phases.files_there == [
                True
            ], name
            assert len(attempts_on_nodes(c, job.id)) == (1 if cluster is not None else 0), name

        base, step = c.model("base"), c.model(jobs["adapt"].result["model_id"])
        assert jobs["pretrain"].result["model_id"] == base.id and step.parent_id == base.id
        assert (
            jobs["fit_nerf"].result["size_bytes"] > 0
            and 0.0 <= jobs["evaluate"].result["miou"][str(c.scene(rooms.a.name).id)] <= 1.0
        )
        with live.services.sessions() as s:
            assert live.services.store.verify(s).ok
        c.close()
    finally:
        live.stop()


# -- Ray only ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ray_service(ray_cluster: RayCluster, rooms: Rooms, tmp_path_factory) -> Iterator[LiveServer]:
    live = start_server(
        test_settings(tmp_path_factory.mktemp("ray-service"), **ray_settings(ray_cluster))
    )
    try:
        with live.client() as c:
            for folder in (rooms.a, rooms.b):
                c.upload_scene_folder(folder)
        yield live
    finally:
        live.stop()


def test_cancel_reaches_a_running_ray_task(ray_service: LiveServer, rooms: Rooms) -> None:
    with ray_service.client() as c:
        job = c.create_job("fit_nerf", scene=rooms.b.name, **LONG_FIT)
        wait_for(lambda: c.job(job.id).message.startswith(FITTING), 120, "the fit to be fitting")
        c.cancel_job(job.id)
        final = c.wait_job(job.id, timeout=60, raise_on_failure=False)
        # Stopped by its own check (not killed after the grace period), with nothing registered.
        assert (
            final.status == "cancelled"
            and final.error == "cancelled by request"
            and final.result is None
        )
        assert final.progress < 0.5
        assert not c.scene(rooms.b.name).has_nerf


def compute_dies(inputs: ParamsInputs, workdir: Path, ctx: JobContext) -> ResultOutputs:
    """A test job whose process dies: what an out-of-memory kill or a crashing driver does."""
    ctx.progress(0.1, "about to die", force=True)
    os._exit(1)


def test_a_task_whose_worker_dies_every_time_fails_after_max_attempts(
    ray_service: LiveServer, monkeypatch
) -> None:
    monkeypatch.setitem(KINDS, "dies", job_kind("dies", compute_dies))
    services = ray_service.services
    with services.sessions() as s:
        job_id = queue.enqueue(s, "dies", {}, None).id
        s.commit()
    with ray_service.client() as c:
        final = c.wait_job(job_id, timeout=120, raise_on_failure=False)
        assert final.status == "failed" and final.attempts == 2
        assert final.error.startswith("its Ray worker was lost (") and final.error.endswith(
            "during attempt 2 of 2; not retried"
        )
        lines = [line.message for line in c.job_log(job_id)]
        assert any(
            m.startswith("re-queued after attempt 1 of 2: its Ray worker was lost") for m in lines
        )
        assert [a for _, _, a in attempts_on_nodes(c, job_id)] == [1, 2]
        assert c.health().status == "ok"


def test_api_restart_hands_a_running_ray_job_back_and_runs_it_again(
    ray_cluster: RayCluster, ray_service: LiveServer, rooms: Rooms
) -> None:
    with ray_service.client() as c:
        job = c.create_job("fit_nerf", scene=rooms.a.name, **LONG_FIT)
        wait_for(lambda: c.job(job.id).message.startswith(FITTING), 120, "the fit to be fitting")
    ray_service.stop()  # the module's server; nothing after this test uses it
    with ray_service.services.sessions() as s:
        back = s.get(Job, job.id)
        assert (
            back.status == "queued"
            and back.attempts == 0
            and back.message == "re-queued: the API is shutting down"
        )
    live = start_server(ray_service.settings)
    try:
        with live.client() as c:
            again = wait_for(
                lambda: (
                    (j := c.job(job.id)).status == "running" and j.message.startswith(FITTING) and j
                ),
                120,
                "the job to run again",
            )
            assert again.attempts == 1 and [a for _, _, a in attempts_on_nodes(c, job.id)] == [1, 1]
            c.cancel_job(job.id)
            assert c.wait_job(job.id, timeout=60, raise_on_failure=False).status == "cancelled"
    finally:
        live.stop()


# -- pieces, without a cluster ---------------------------------------------------------------


def test_the_default_executor_never_imports_ray() -> None:
    code = (
        "import sys; from server.app import create_app; "
        "import server.executors.embedded, server.jobs.kinds; print('ray' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_a_task_without_a_reserved_gpu_runs_on_the_cpu() -> None:
    """``evaluate`` reserves no GPU: its task must not pick one (which another job may hold)."""
    from server.executors.ray_cluster import task_device
    from server.jobs.kinds import KINDS

    assert task_device("auto", 0) == task_device("cuda", 0) == "cpu"
    assert task_device("auto", 1) == "auto" and task_device("cuda:1", 1) == "cuda:1"
    assert not KINDS["evaluate"].gpu and KINDS["fit_nerf"].gpu


def test_a_lost_workers_reason_keeps_whole_sentences() -> None:
    """The status line of a job re-queued after its node died says what Ray said, in whole
    sentences (Ray's message runs to several sentences of advice)."""
    from ray.exceptions import NodeDiedError

    from server.executors.ray_cluster import lost_worker_reason

    message = (
        "Task failed due to the node (where this task was running) dying. "
        "The node (IP: 127.0.0.2, node ID: " + "ab" * 28 + ") has been marked dead because the "
        "detector has missed too many heartbeats from it. "
        "This can happen when a (1) raylet crashes unexpectedly (OOM, etc.) "
        "(2) raylet has lagging heartbeats."
    )
    reason = lost_worker_reason(NodeDiedError(message))
    assert reason.startswith("its Ray worker was lost (NodeDiedError: Task failed due to the node")
    assert reason.endswith("missed too many heartbeats from it.)") and len(reason) < 360
    assert (
        queue.brief(message, 70)
        == "Task failed due to the node (where this task was running) dying."
    )
    cut = queue.brief("x " * 20 + "y" * 100, 50)  # no sentence fits: cut at a word, and say so
    assert len(cut) <= 50 and cut.endswith("…") and not cut.endswith(" …")
    assert queue.brief("first line\nsecond line", 100) == "first line" and queue.brief("", 10) == ""


def test_folders_of_killed_tasks_are_removed_by_the_next_task(tmp_path: Path) -> None:
    """A task's folder on its node outlives a killed worker process (its clean-up never ran);
    the next task on the node removes it, and never a folder of a live process or another host."""
    from server.executors.remote import TASK_OWNER_FILE, remove_dead_task_folders, task_folder

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    killed = task_folder(7, tmp_path)
    (killed / TASK_OWNER_FILE).write_text(f"{socket.gethostname()} {dead.pid}\n")
    # Killed, not yet reaped by its parent (a worker whose raylet was killed with it).
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])
    wait_for(
        lambda: Path(f"/proc/{zombie.pid}/stat").read_text().rpartition(")")[2].split()[0] == "Z",
        30,
        "a zombie",
    )
    unreaped = task_folder(6, tmp_path)
    (unreaped / TASK_OWNER_FILE).write_text(f"{socket.gethostname()} {zombie.pid}\n")
    (killed / "inputs").mkdir()
    (killed / "inputs" / "blob").write_bytes(b"x" * 1000)
    running = task_folder(8, tmp_path)  # this process's: alive
    elsewhere = task_folder(9, tmp_path)
    (elsewhere / TASK_OWNER_FILE).write_text(f"another-host-{socket.gethostname()} {dead.pid}\n")
    unrelated = tmp_path / "csa-job-notes"
    unrelated.mkdir()
    assert sorted(remove_dead_task_folders(tmp_path)) == sorted([killed, unreaped])
    zombie.wait()
    assert not killed.exists() and not unreaped.exists()
    assert running.is_dir() and elsewhere.is_dir() and unrelated.is_dir()
