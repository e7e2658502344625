"""A user with one scene: pre-train on it, then adapt the network to the same scene.

The adapt job reads the target scene and the lineage's pre-training scenes into its scratch
folder; here they are one scene, read twice (once as the target, once for the pre-training
replay), and the step must run as it does on any other scene (embedded executor; the Ray
executor's task reads its scenes with the same ``server.jobs.inputs.load_scene``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from server import capabilities
from tests.server.conftest import SCENE_SIZE, LiveServer, start_server, test_settings

pytestmark = pytest.mark.skipif(
    not all(capabilities.available(c) for c in ("seg", "nerf", "adapt")),
    reason="needs csa_core.seg, csa_core.nerf and csa_core.adapt",
)


@pytest.fixture(scope="module")
def one_scene_service(tmp_path_factory) -> Iterator[tuple[LiveServer, Path]]:
    from csa_core.data.synth import synthesize

    data = tmp_path_factory.mktemp("one-scene")
    (room,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=0
    )
    live = start_server(test_settings(data / "service"))
    try:
        with live.client() as c:
            deadline = time.monotonic() + 10
            while c.health().workers_alive < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            c.upload_scene_folder(room)
            base = c.wait_job(
                c.pretrain([room.name], epochs=1, batch_size=4, name="base").id, timeout=300
            )
            assert base.status == "succeeded", base.error
        yield live, room
    finally:
        live.stop()


def test_adapting_to_the_pretraining_scene_succeeds(one_scene_service) -> None:
    live, room = one_scene_service
    with live.client() as c:
        done = c.wait_job(
            c.adapt(room.name, model="base", preset="tiny").id, timeout=600, raise_on_failure=False
        )
        log = "\n".join(line.message for line in c.job_log(done.id, tail=200))
        assert done.status == "succeeded", f"{done.error}\n{log[-3000:]}"
        new = c.model(done.result["model_id"])
        assert (
            new.name == "base-step1"
            and new.parent_id == c.model("base").id
            and new.adapted_scene == room.name
        )
        # Scored on the scene it adapted to (labelled), before and after the step.
        assert (
            0.0 <= new.metrics["val_miou"] <= 1.0 and 0.0 <= new.metrics["before_val_miou"] <= 1.0
        )
        m = c.continual_metrics(lineage="base")
        assert [s.scene for s in m.steps] == [room.name] and m.R[0][0] == pytest.approx(
            new.metrics["val_miou"]
        )
    # The job's scratch folder (the scene written into it once) goes right after the job ended.
    work = live.settings.resolved_work_dir
    deadline = time.monotonic() + 30
    while [p for p in work.iterdir() if p.name.startswith("job-")] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [p for p in work.iterdir() if p.name.startswith("job-")]
