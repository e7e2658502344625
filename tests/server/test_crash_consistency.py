"""Crash consistency with real processes: ``csa serve`` killed with SIGKILL at each fault
point of its write paths (server/faults.py), then ``csa doctor`` and a restart.

One data folder and database go through a chain of servers, each armed at the next point.
After each kill: the request that was cut got no answer, every write answered before it is
there, nothing of the cut one is visible, ``csa doctor --dry-run`` reports what the crash
left, ``csa doctor`` removes it (and re-queues the interrupted job as the queue's recovery
does) and a second ``--dry-run`` finds nothing. The interrupted job is re-queued once and
finishes on the next server. Runs on SQLite, and on PostgreSQL where the fixtures provide it.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from sqlalchemy import func, select

from client import CSAClient
from client.errors import CSAConnectionError, CSAHTTPError
from server import capabilities, faults
from server.artifacts import ArtifactStore
from server.db.models import NerfCheckpoint
from server.db.session import make_engine, make_sessionmaker
from server.doctor import examine
from tests.server.conftest import (
    API_KEY,
    BACKENDS,
    SCENE_SIZE,
    database_url,
    free_port,
    start_server,
    test_settings,
)
from tests.server.test_worker_crash import REPO, start_api, wait_for

pytestmark = pytest.mark.skipif(
    not capabilities.available("seg"), reason="model uploads need csa_core.seg"
)

TINY_NERF = {"steps": 30, "rays_per_step": 128, "occupancy_resolution": 16, "log2_table_size": 10}
SIGKILLED = -9


def csa(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """A ``csa`` command in its own process, with no CSA_* settings of this environment."""
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("CSA_")},
        "PYTHONPATH": str(REPO),
    }
    return subprocess.run(
        [sys.executable, "-m", "csa_core.cli.main", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def found(report: str) -> dict[str, int]:
    """``csa doctor``'s counts by line title ("blob files without an artifact row": 3)."""
    return {m[1]: int(m[2]) for m in re.finditer(r"^(\w[^:\n]*): (\d+)", report, re.M)}


class Chain:
    """Servers started one after another on one data folder and database."""

    def __init__(self, tmp: Path, db_url: str | None):
        self.tmp, self.db_url = tmp, db_url
        self.data = tmp / "data"
        self.log = tmp / "api.log"
        self.proc: subprocess.Popen | None = None
        self.port = 0

    def db_args(self) -> list[str]:
        return ["--data-dir", str(self.data)] + (
            ["--database-url", self.db_url] if self.db_url else []
        )

    def start(self, fault: str | None = None) -> CSAClient:
        self.port = free_port()
        extra = {"CSA_FAULT_POINT": fault} if fault else {}
        self.proc = start_api(self.data, self.port, self.log, self.db_url, extra)
        c = CSAClient(f"http://127.0.0.1:{self.port}", api_key=API_KEY, timeout=120)
        wait_for(
            lambda: c.health().workers_alive == 1, 120, "the API to start", self.proc, self.log
        )
        return c

    def killed(self) -> None:
        """The server died at its fault point (SIGKILL), not of something else."""
        assert self.proc is not None
        code = self.proc.wait(timeout=120)
        assert code == SIGKILLED, (
            f"the API exited with {code}, not by SIGKILL: {self.log.read_text()[-2000:]}"
        )

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=60)

    def nerfs(self) -> int:
        """NeRF checkpoints in the database (read directly: a killed job has no API to ask)."""
        engine = make_engine(
            test_settings(self.data, database_url=self.db_url).resolved_database_url
        )
        try:
            with make_sessionmaker(engine)() as s:
                return s.scalar(select(func.count()).select_from(NerfCheckpoint)) or 0
        finally:
            engine.dispose()

    def doctor(self, expect: dict[str, int]) -> None:
        """``--dry-run`` reports ``expect`` (counts by title; every other count 0), the repair
        exits 0, and a second ``--dry-run`` finds nothing."""
        dry = csa("doctor", "--dry-run", *self.db_args(), cwd=self.tmp)
        counts = found(dry.stdout)
        assert {k: v for k, v in counts.items() if v} == expect, dry.stdout
        assert dry.returncode == (1 if expect else 0), dry.stdout + dry.stderr
        fix = csa("doctor", *self.db_args(), cwd=self.tmp)
        assert fix.returncode == 0, fix.stdout + fix.stderr
        assert found(fix.stdout) == counts, fix.stdout  # what it repaired is what it reported
        # Looked at again (here, not in a third process): nothing is left.
        settings = test_settings(self.data, database_url=self.db_url)
        engine = make_engine(settings.resolved_database_url)
        try:
            again = examine(
                make_sessionmaker(engine),
                ArtifactStore(settings.resolved_artifact_dir),
                settings.resolved_work_dir,
                repair=False,
                min_age_s=0,
                grace_s=0,
                lease_seconds=settings.lease_seconds,
                max_attempts=settings.max_attempts,
            )
        finally:
            engine.dispose()
        assert again.problems == 0, again.lines()


def frame_parts(room: Path, name: str) -> dict:
    return {
        "color": room / "color" / f"{name}.png",
        "depth": room / "depth" / f"{name}.png",
        "pose": room / "pose" / f"{name}.txt",
        "labels": room / "label-nyu40" / f"{name}.png",
        "intrinsics": room / "intrinsic" / "intrinsic_color.txt",
        "depth_intrinsics": room / "intrinsic" / "intrinsic_depth.txt",
    }


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_killed_at_every_fault_point_loses_no_acknowledged_write_and_leaves_no_orphan(
    request, backend: str, tmp_path: Path
) -> None:
    from csa_core.data.synth import synthesize
    from csa_core.seg.checkpoint import save_checkpoint
    from csa_core.seg.models import build_model

    (room,) = synthesize(
        tmp_path / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=5
    )
    checkpoint = (
        save_checkpoint(tmp_path / "m.safetensors", build_model()) and tmp_path / "m.safetensors"
    )
    model_sha = hashlib.sha256(checkpoint.read_bytes()).hexdigest()
    chain = Chain(tmp_path, database_url(request, backend))
    try:
        # 1. A frame's blobs are written, its row not committed.
        with chain.start("frame.blobs_written:2") as c:
            c.create_scene("room")
            first = c.upload_frame("room", name="0", **frame_parts(room, "0"))
            with pytest.raises(CSAConnectionError):
                c.upload_frame("room", name="1", **frame_parts(room, "1"))
        chain.killed()
        chain.doctor({"blob files without an artifact row": 3})

        # 2. An archive killed after three of its eight frames were stored (uncommitted).
        with chain.start("archive.frame_stored:3") as c:
            assert [f.name for f in c.frames("room")] == ["0"] and c.frames("room")[
                0
            ].id == first.id
            with pytest.raises(CSAConnectionError):
                c.upload_scene_folder(room, scene="room")
        chain.killed()
        # Frames 1 and 2 (frame 0 is stored already), and the archive's folder in the work dir.
        chain.doctor(
            {"blob files without an artifact row": 6, "scratch folders of dead jobs and uploads": 1}
        )

        # 3. A model upload killed with its checkpoint half in the store: a temporary file.
        with chain.start("artifact.tmp_written:1") as c:
            assert [f.name for f in c.frames("room")] == ["0"]
            with pytest.raises(CSAConnectionError):
                c.register_model(checkpoint, name="m")
        chain.killed()
        chain.doctor(
            {"half-written temporary files": 1, "scratch folders of dead jobs and uploads": 1}
        )

        # 4. A model upload killed with its checkpoint in the store, its row not committed.
        with chain.start("artifact.file_stored:1") as c:
            assert c.models() == []
            with pytest.raises(CSAConnectionError):
                c.register_model(checkpoint, name="m")
        chain.killed()
        chain.doctor(
            {"blob files without an artifact row": 1, "scratch folders of dead jobs and uploads": 1}
        )

        # 5. A NeRF fit killed between its computation and the registration of its outputs.
        with chain.start("job.computed:1") as c:
            assert c.models() == []
            _, archive = c.upload_scene_folder(room, scene="room")
            assert archive.unchanged == ["0"] and len(archive.added) == 7
            assert c.register_model(checkpoint, name="m").sha256 == model_sha
            job = c.create_job("fit_nerf", scene="room", labels="ground_truth", **TINY_NERF)
            wait_for(lambda: chain.proc.poll() is not None, 300, "the API to die at job.computed")
        chain.killed()
        assert chain.nerfs() == 0  # computed, not registered: nothing of it is visible
        chain.doctor(
            {"jobs running with no live owner": 1, "scratch folders of dead jobs and uploads": 1}
        )

        # 6. The job, re-queued once by the repair, runs again and succeeds; a second fit is
        # killed inside the transaction that registers its NeRF (its blob is written).
        with chain.start("job.registering:2") as c:
            done = c.wait_job(job.id, timeout=300)
            assert done.status == "succeeded" and done.attempts == 2
            lines = [line.message for line in c.job_log(job.id, tail=1000)]
            assert sum(m.startswith("re-queued after attempt 1 of 2") for m in lines) == 1
            assert c.scene_nerf("room").id == done.result["nerf_id"]
            second = c.create_job(
                "fit_nerf",
                scene="room",
                labels="ground_truth",
                steps=40,
                **{k: v for k, v in TINY_NERF.items() if k != "steps"},
            )
            wait_for(
                lambda: chain.proc.poll() is not None, 300, "the API to die at job.registering"
            )
        chain.killed()
        assert chain.nerfs() == 1  # the first job's; the second's rows were never committed
        chain.doctor(
            {
                "blob files without an artifact row": 1,
                "jobs running with no live owner": 1,
                "scratch folders of dead jobs and uploads": 1,
            }
        )

        # 7. No fault: everything answered is there and intact, and the second job finishes.
        with chain.start() as c:
            again = c.wait_job(second.id, timeout=300)
            assert again.status == "succeeded" and again.attempts == 2
            frames = c.frames("room")
            assert [f.name for f in frames] == [str(i) for i in range(8)]
            assert frames[0].id == first.id
            assert [m.name for m in c.models()] == ["m"]
            downloaded = c.download_model("m", tmp_path / "down.safetensors")
            assert hashlib.sha256(downloaded.read_bytes()).hexdigest() == model_sha
            assert c.scene_nerf("room").id == again.result["nerf_id"]
        chain.stop()
        chain.doctor({})
    finally:
        chain.stop()


def look(settings, repair: bool = False):
    """``csa doctor``'s examination in this process, with no age limit."""
    engine = make_engine(settings.resolved_database_url)
    try:
        return examine(
            make_sessionmaker(engine),
            ArtifactStore(settings.resolved_artifact_dir),
            settings.resolved_work_dir,
            repair=repair,
            min_age_s=0,
            grace_s=0,
            lease_seconds=settings.lease_seconds,
            max_attempts=settings.max_attempts,
        )
    finally:
        engine.dispose()


def test_a_full_disk_answers_507_and_leaves_nothing_half_written(
    synth_scene: Path, tmp_path: Path
) -> None:
    """Writes into a full data folder (``OSError(ENOSPC)`` from the fault point at the artifact
    store's write) are answered 507 naming the cause; no row, no temporary file and no upload
    folder is left, only whole blobs of the failed request, which the sweep (or csa doctor)
    removes; once there is space the same uploads succeed."""
    from csa_core.seg.checkpoint import save_checkpoint
    from csa_core.seg.models import build_model

    checkpoint = tmp_path / "m.safetensors"
    save_checkpoint(checkpoint, build_model())
    live = start_server(test_settings(tmp_path / "data", embedded_worker=False))
    settings = live.settings
    try:
        with live.client() as c:
            c.create_scene("full")
            attempts = [
                (
                    "artifact.write:2:enospc",
                    lambda: c.upload_frame("full", name="0", **frame_parts(synth_scene, "0")),
                ),
                (
                    "artifact.write:1:enospc",
                    lambda: c.upload_scene_folder(synth_scene, scene="full"),
                ),
                ("artifact.write:1:enospc", lambda: c.register_model(checkpoint, name="m")),
            ]
            for fault, write in attempts:
                faults.configure(fault)
                try:
                    with pytest.raises(CSAHTTPError) as refused:
                        write()
                finally:
                    faults.configure(None)
                err = refused.value
                assert (err.status, err.code) == (507, "insufficient_storage"), str(err)
                assert "data folder is full (No space left on device)" in str(err) and str(
                    tmp_path
                ) not in str(err)
                assert c.frames("full") == [] and c.models() == []
                assert list((settings.resolved_artifact_dir / "tmp").iterdir()) == []
                assert list(settings.resolved_work_dir.iterdir()) == []
            # The frame's colour image went in whole before the depth write failed: one
            # unrecorded blob, nothing else.
            report = look(settings)
            assert (len(report.orphan_blobs), report.problems) == (1, 1), report.lines()
            assert look(settings, repair=True).orphan_blobs == report.orphan_blobs
            assert c.upload_frame("full", name="0", **frame_parts(synth_scene, "0")).created
            assert c.register_model(checkpoint, name="m").name == "m"
        assert look(settings).problems == 0
    finally:
        faults.configure(None)
        live.stop()


def test_postgresql_restarted_under_traffic_the_service_recovers_by_itself(tmp_path: Path) -> None:
    """A PostgreSQL server that this test starts itself (never the shared one) is restarted
    while a client keeps reading: reads answer 200 before, 503 naming the database (never 500)
    while it is down, and 200 again after it is back, without restarting the service; a write
    after the restart is stored."""
    import threading

    from tests.pg import PostgresDatabases, PostgresUnavailable, PrivateServer

    try:
        pg = PrivateServer.start()
    except PostgresUnavailable as e:
        pytest.skip(f"cannot start a private PostgreSQL server: {e}")
    databases = PostgresDatabases(pg.url, server=pg)
    live = None
    try:
        live = start_server(
            test_settings(tmp_path / "data", database_url=databases.create(), embedded_worker=False)
        )
        seen: list[tuple[str, int | str]] = []  # (phase, status or error)
        phase = ["before"]
        stop = threading.Event()

        def read_forever() -> None:
            with live.client(timeout=30) as c:
                while not stop.is_set():
                    try:
                        c.scenes()
                        seen.append((phase[0], 200))
                    except CSAHTTPError as e:
                        seen.append((phase[0], f"{e.status} {e.code}"))
                    except CSAConnectionError as e:  # the service itself must stay up
                        seen.append((phase[0], f"no answer: {e}"))
                    stop.wait(0.05)

        with live.client() as c:
            c.create_scene("before-restart")
        reader = threading.Thread(target=read_forever, daemon=True)
        reader.start()
        wait_for(lambda: len(seen) >= 5, 60, "reads before the restart")
        phase[0] = "down"
        stopped = pg._run(
            str(pg.bin_dir / "pg_ctl"), "-D", "data", "-m", "fast", "-w", "stop", timeout=60
        )
        assert stopped.returncode == 0, stopped.stderr
        wait_for(
            lambda: sum(p == "down" for p, _ in seen) >= 5, 60, "reads while the database is down"
        )
        started = pg._run(
            str(pg.bin_dir / "pg_ctl"),
            "-D",
            "data",
            "-l",
            "server.log",
            "-w",
            "restart",
            timeout=60,
        )
        assert started.returncode == 0, started.stderr
        phase[0] = "back"
        wait_for(
            lambda: any(p == "back" and s == 200 for p, s in seen),
            60,
            "a read to succeed after the restart",
        )
        first_ok = next(i for i, (p, s) in enumerate(seen) if p == "back" and s == 200)
        wait_for(lambda: len(seen) >= first_ok + 20, 60, "more reads after the restart")
        stop.set()
        reader.join(30)

        assert all(s == 200 for p, s in seen if p == "before"), seen
        assert all(s == 200 for s in [s for _, s in seen[first_ok:]]), seen[first_ok:]
        outage = {s for p, s in seen if p != "before" and s != 200}
        assert outage and outage <= {"503 database_unavailable"}, seen
        with live.client() as c:
            c.create_scene("after-restart")
            assert [s.name for s in c.scenes()] == ["before-restart", "after-restart"]
    finally:
        if live is not None:
            live.stop()
        databases.close()


def test_fault_points_are_off_unless_named_and_a_bad_setting_is_refused_naming_it() -> None:
    assert faults.active() is None  # the tests run with CSA_FAULT_POINT unset
    for name in faults.POINTS:
        faults.point(name)  # off: nothing happens
    assert faults.parse("job.computed") == faults.Fault("job.computed", 1, "kill")
    assert faults.parse("artifact.write:3:enospc") == faults.Fault("artifact.write", 3, "enospc")
    for value, problem in [
        ("job.compute", "unknown point 'job.compute'"),
        ("job.computed:0", "COUNT must be a whole number >= 1, got '0'"),
        ("job.computed:x", "COUNT must be a whole number >= 1, got 'x'"),
        ("job.computed:1:explode", "ACTION must be one of kill, enospc, got 'explode'"),
        ("a:1:kill:more", "expected NAME[:COUNT[:ACTION]]"),
    ]:
        with pytest.raises(ValueError) as refused:
            faults.parse(value)
        assert str(refused.value).startswith(f"CSA_FAULT_POINT={value!r}: ") and problem in str(
            refused.value
        )
    try:
        faults.configure("frame.blobs_written:2:enospc")
        faults.point("frame.blobs_written")  # the first hit passes
        faults.point("job.computed")  # another point: nothing
        for _ in range(2):  # the second hit and every later one: a full disk stays full
            with pytest.raises(OSError) as full:
                faults.point("frame.blobs_written")
            assert full.value.errno == errno.ENOSPC
    finally:
        faults.configure(None)
