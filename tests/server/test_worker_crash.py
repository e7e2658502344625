"""The API process killed with SIGKILL in the middle of a job (embedded executor): when the
API starts again the job is re-queued with the reason and runs again (never left
``running``), its lineage is freed, and every stored frame and checkpoint still verifies
against its checksum."""

from __future__ import annotations

import hashlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from client.errors import CSAConnectionError
from server import capabilities
from server.db.models import Worker as WorkerRow
from server.jobs import queue
from tests.server.conftest import API_KEY, SCENE_SIZE, free_port, start_server, test_settings

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not capabilities.available("seg"), reason="needs csa_core.seg for a real job to interrupt"
)


def start_api(
    data_dir: Path,
    port: int,
    log: Path,
    database_url: str | None = None,
    extra_env: dict[str, str] | None = None,
) -> subprocess.Popen:
    """``csa serve`` in its own process, with the embedded executor (on ``database_url``, and
    ``extra_env`` such as ``CSA_FAULT_POINT`` when given)."""
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("CSA_")},  # no stray settings
        "CSA_API_KEYS": API_KEY,
        "CSA_WORKER_POLL_SECONDS": "0.1",
        "CSA_HEARTBEAT_SECONDS": "0.3",
        "CSA_LEASE_SECONDS": "3",
        "CSA_TORCH_THREADS": "1",
        "CSA_DEVICE": "cpu",
        "PYTHONPATH": str(REPO),
        **(extra_env or {}),
    }
    args = [
        sys.executable,
        "-m",
        "csa_core.cli.main",
        "serve",
        "--data-dir",
        str(data_dir),
        "--port",
        str(port),
        "--log-level",
        "warning",
    ]
    if database_url is not None:
        args += ["--database-url", database_url]
    with open(log, "ab") as out:
        return subprocess.Popen(args, cwd=log.parent, env=env, stdout=out, stderr=subprocess.STDOUT)


def wait_for(
    predicate,
    timeout: float,
    what: str,
    proc: subprocess.Popen | None = None,
    log: Path | None = None,
):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = predicate()
        except CSAConnectionError:  # the server is not listening yet
            value = None
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            raise AssertionError(
                f"the API exited ({proc.returncode}) while waiting for {what}: "
                f"{log.read_text()[-2000:] if log else ''}"
            )
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_killed_api_process_leaves_no_running_job_and_loses_nothing(tmp_path: Path) -> None:
    from client import CSAClient
    from csa_core.data.synth import synthesize

    data_dir = tmp_path / "data"
    log = tmp_path / "api.log"
    (room,) = synthesize(
        tmp_path / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="studio", seed=4
    )
    port = free_port()
    api = start_api(data_dir, port, log)
    try:
        with CSAClient(f"http://127.0.0.1:{port}", api_key=API_KEY, timeout=30) as c:
            wait_for(lambda: c.health().workers_alive == 1, 120, "the API to start", api, log)
            c.upload_scene_folder(room)
            base = c.wait_job(
                c.pretrain([room.name], epochs=1, batch_size=4, name="base").id, timeout=300
            )
            model = c.model(base.result["model_id"])
            long = c.pretrain([room.name], epochs=5000, batch_size=4, name="long")
            wait_for(
                lambda: c.job(long.id).message.startswith("training"),
                120,
                "the long job to train",
                api,
                log,
            )
            running = c.job(long.id)
            assert running.status == "running" and running.worker_id.split(":")[1] == str(api.pid)
            scratch = [
                p for p in (data_dir / "work").iterdir() if p.name.startswith(f"job-{long.id}-")
            ]
            assert scratch
        api.send_signal(signal.SIGKILL)
        api.wait(timeout=30)
    finally:
        if api.poll() is None:
            api.kill()
            api.wait(timeout=30)

    # The API starts again on the same data: its executor re-queues the job and runs it again.
    live = start_server(test_settings(data_dir))
    try:
        with live.client() as c:
            again = wait_for(
                lambda: (j := c.job(long.id)).attempts == 2 and j.status == "running" and j,
                60,
                "the job's second attempt",
            )
            assert again.worker_id != running.worker_id
            lines = [line.message for line in c.job_log(long.id)]
            requeued = next(m for m in lines if m.startswith("re-queued after attempt 1 of 2"))
            assert f"(pid {api.pid}) is gone" in requeued
            assert not any(
                p.exists() for p in scratch
            )  # the killed attempt's scratch folder went at start-up
            assert c.cancel_job(long.id).status in ("running", "cancelled")
            final = c.wait_job(long.id, timeout=60, raise_on_failure=False)
            assert final.status == "cancelled" and final.result is None

            # The killed job registered nothing; what was stored before is intact.
            assert [m.name for m in c.models()] == ["base"]
            assert c.scene(room.name).num_frames == 8
            services = live.services
            with services.sessions() as s:
                report = services.store.verify(s)
            assert report.ok and report.checked >= 8 * 3 + 1
            downloaded = c.download_model("base", tmp_path / "base.safetensors")
            assert hashlib.sha256(downloaded.read_bytes()).hexdigest() == model.sha256
    finally:
        live.stop()


def test_lost_job_fails_after_max_attempts(tmp_path: Path) -> None:
    """The second loss of the same job is final: failed, with the reason."""
    live = start_server(test_settings(tmp_path / "data", embedded_worker=False))
    try:
        services = live.services
        with services.sessions() as s:
            job = queue.enqueue(
                s, "evaluate", {"model_id": 1, "scene_ids": [], "split": "val"}, None
            )
            s.commit()
            job_id = job.id
        for attempt in range(2):
            dead = subprocess.Popen([sys.executable, "-c", "pass"])
            dead.wait()
            owner = f"{socket.gethostname()}:{dead.pid}:dead{attempt}"
            with services.sessions() as s:
                s.add(
                    WorkerRow(
                        id=owner, hostname=socket.gethostname(), pid=dead.pid, mode="embedded"
                    )
                )
                s.commit()
            claimed = queue.claim_next(services.sessions, owner, 30, {"evaluate"})
            assert claimed is not None and claimed.id == job_id
            assert queue.recover_stale_jobs(services.sessions, 2) == [job_id]
        with live.client() as c:
            final = c.job(job_id)
        assert (
            final.status == "failed" and "is gone during attempt 2 of 2; not retried" in final.error
        )
    finally:
        live.stop()
