"""A standalone worker process killed with SIGKILL in the middle of a job: the job is
re-queued with a reason (never left ``running``), its lineage is freed, and every stored
frame and checkpoint still verifies against its checksum."""

from __future__ import annotations

import hashlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from server import capabilities
from server.db.models import Worker as WorkerRow
from server.jobs import queue
from server.worker import Worker
from tests.server.conftest import API_KEY, SCENE_SIZE, LiveServer, start_server, test_settings

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(not capabilities.available("seg"), reason="needs csa_core.seg for a real job to interrupt")


def start_worker(data_dir: Path, log: Path) -> subprocess.Popen:
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("CSA_")},  # no stray settings
        "CSA_API_KEYS": API_KEY,
        "CSA_WORKER_POLL_SECONDS": "0.1",
        "CSA_HEARTBEAT_SECONDS": "0.3",
        "CSA_LEASE_SECONDS": "3",
        "CSA_TORCH_THREADS": "1",
        "CSA_DEVICE": "cpu",
        "PYTHONPATH": str(REPO),
    }
    with open(log, "ab") as out:
        return subprocess.Popen([sys.executable, "-m", "csa_core.cli.main", "worker", "--data-dir", str(data_dir)], cwd=log.parent, env=env, stdout=out, stderr=subprocess.STDOUT)


def wait_for(predicate, timeout: float, what: str, proc: subprocess.Popen | None = None, log: Path | None = None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"worker exited ({proc.returncode}) while waiting for {what}: {log.read_text()[-2000:] if log else ''}")
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def api_only(tmp_path: Path) -> Iterator[LiveServer]:
    live = start_server(test_settings(tmp_path / "data", embedded_worker=False))
    yield live
    live.stop()


def test_killed_worker_leaves_no_running_job_and_loses_nothing(api_only: LiveServer, tmp_path: Path) -> None:
    from csa_core.data.synth import synthesize

    data_dir = api_only.settings.data_dir
    log = tmp_path / "worker.log"
    (room,) = synthesize(tmp_path / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="studio", seed=4)
    worker = start_worker(data_dir, log)
    try:
        with api_only.client() as c:
            c.upload_scene_folder(room)
            base = c.wait_job(c.pretrain([room.name], epochs=1, batch_size=4, name="base").id, timeout=300)
            model = c.model(base.result["model_id"])

            long = c.pretrain([room.name], epochs=5000, batch_size=4, name="long")
            wait_for(lambda: c.job(long.id).message.startswith("training"), 120, "the long job to train", worker, log)
            time.sleep(1.0)
            running = c.job(long.id)
            assert running.status == "running" and running.worker_id.split(":")[1] == str(worker.pid)
            worker.send_signal(signal.SIGKILL)
            worker.wait(timeout=30)

            assert c.job(long.id).status == "running"  # nobody has noticed yet
            # What every worker does when it starts or polls: recover jobs of dead workers.
            services = api_only.services
            assert queue.recover_stale_jobs(services.sessions, services.settings.max_attempts) == [long.id]
            requeued = c.job(long.id)
            assert requeued.status == "queued" and requeued.worker_id is None and requeued.attempts == 1
            assert "re-queued after attempt 1 of 2" in requeued.message and f"(pid {worker.pid}) is gone" in requeued.message
            assert any("re-queued" in line.message for line in c.job_log(long.id))

            # The killed job registered nothing; what was stored before is intact.
            assert [m.name for m in c.models()] == ["base"]
            assert c.scene(room.name).num_frames == 8
            with services.sessions() as s:
                report = services.store.verify(s)
            assert report.ok and report.checked >= 8 * 3 + 1
            downloaded = c.download_model("base", tmp_path / "base.safetensors")
            assert hashlib.sha256(downloaded.read_bytes()).hexdigest() == model.sha256

            # The killed job's scratch folder goes when the next worker starts; cancel the job
            # so that it does not run again.
            scratch = [p for p in services.settings.resolved_work_dir.iterdir() if p.name.startswith(f"job-{long.id}-")]
            assert scratch
            assert c.cancel_job(long.id).status == "cancelled"
            Worker(services)._register()
            assert not any(p.exists() for p in scratch)
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.wait(timeout=30)


def test_lost_job_fails_after_max_attempts(api_only: LiveServer) -> None:
    """The second loss of the same job is final: failed, with the reason."""
    services = api_only.services
    with services.sessions() as s:
        job = queue.enqueue(s, "evaluate", {"model_id": 1, "scene_ids": [], "split": "val"}, None)
        s.commit()
        job_id = job.id
    for attempt in range(2):
        dead = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.wait()
        worker_id = f"{socket.gethostname()}:{dead.pid}:dead{attempt}"
        with services.sessions() as s:
            s.add(WorkerRow(id=worker_id, hostname=socket.gethostname(), pid=dead.pid, mode="standalone"))
            s.commit()
        claimed = queue.claim_next(services.sessions, worker_id, 30, {"evaluate"})
        assert claimed is not None and claimed.id == job_id
        assert queue.recover_stale_jobs(services.sessions, 2) == [job_id]
    with api_only.client() as c:
        final = c.job(job_id)
    assert final.status == "failed" and "is gone during attempt 2 of 2; not retried" in final.error
