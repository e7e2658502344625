"""``csa-client health`` and ``csa-client memory`` print readable fields, not raw JSON: against a
real server with its embedded worker, after a real (tiny) NeRF fit put a scene in the bank."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from client.cli import main as cli_main
from server import capabilities
from tests.server.conftest import API_KEY, SCENE_SIZE, LiveServer, start_server, test_settings

pytestmark = pytest.mark.skipif(
    not capabilities.available("nerf"), reason="needs csa_core.nerf for a real fit"
)

TINY_NERF = {"steps": 60, "rays_per_step": 256, "occupancy_resolution": 32, "log2_table_size": 12}


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Iterator[LiveServer]:
    from csa_core.data.synth import synthesize

    data = tmp_path_factory.mktemp("client-cli")
    (room,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=4
    )
    live = start_server(test_settings(data / "service"))
    try:
        with live.client() as c:
            deadline = time.monotonic() + 10
            while c.health().workers_alive < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            c.upload_scene_folder(room)
            fit = c.wait_job(
                c.create_job("fit_nerf", scene=room.name, labels="ground_truth", **TINY_NERF).id,
                timeout=300,
            )
            assert fit.status == "succeeded", fit.error
        yield live
    finally:
        live.stop()


def run(live: LiveServer, capsys, *args: str) -> tuple[int, str]:
    code = cli_main(["--url", live.url, "--api-key", API_KEY, *args])
    return code, capsys.readouterr().out


def test_health_names_each_capability_as_available_or_why_not(service: LiveServer, capsys) -> None:
    code, out = run(service, capsys, "health")
    assert code == 0 and "null" not in out and "{" not in out
    assert "status: ok" in out and "workers alive 1" in out
    for name, reason in capabilities.report().items():  # what the server reports
        assert f"  {name}: {'available' if reason is None else f'not available ({reason})'}" in out
    code, raw = run(service, capsys, "health", "--json")  # the answer itself, for scripts
    assert code == 0 and '"capabilities"' in raw


def test_memory_prints_the_quality_as_fields(service: LiveServer, capsys) -> None:
    with service.client() as c:
        (entry,) = c.memory().entries
    code, out = run(service, capsys, "memory")
    assert code == 0 and "{" not in out and '"' not in out  # no JSON in the table
    q = entry.quality
    assert (
        f"val psnr {q['val_psnr']:.1f} dB" in out and f"train psnr {q['train_psnr']:.1f} dB" in out
    )
    assert (
        f"val depth mae {q['val_depth_mae_m']:.3f} m" in out
        and f"steps {TINY_NERF['steps']}" in out
    )
    assert (
        f"fit {q['fit_seconds']:.1f} s" in out and entry.scene in out and entry.labels_source in out
    )
