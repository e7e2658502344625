"""Long jobs inside the core library: progress and cancellation from the core's per-epoch
callback, and an adaptation step on a scene uploaded without ground truth.

One real uvicorn server with its embedded worker; scenes are tiny procedural rooms (8 frames
of 40x30) and jobs use tiny settings, so the module runs in well under a minute on a CPU.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from client import CSAClient
from server import capabilities
from tests.server.conftest import SCENE_SIZE, LiveServer, start_server, test_settings

pytestmark = pytest.mark.skipif(
    not capabilities.available("seg"), reason="needs csa_core.seg for real training jobs"
)

needs_adapt = pytest.mark.skipif(
    not (capabilities.available("adapt") and capabilities.available("nerf")),
    reason="needs csa_core.adapt and csa_core.nerf",
)


@dataclass
class Service:
    live: LiveServer
    client: CSAClient
    labelled: str  # a room uploaded with its NYU40 ground truth
    unlabelled: str  # a room uploaded without any labels


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Iterator[Service]:
    from csa_core.data.synth import synthesize

    data = tmp_path_factory.mktemp("progress")
    (labelled,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="apartment", seed=1
    )
    (unlabelled,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=2
    )
    shutil.rmtree(unlabelled / "label-nyu40")  # the product's normal case: no ground truth at all
    live = start_server(test_settings(data / "service"))
    try:
        with live.client() as client:
            deadline = time.monotonic() + 10
            while client.health().workers_alive < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            scene, _ = client.upload_scene_folder(labelled)
            assert scene.num_labelled_frames == 8
            scene, _ = client.upload_scene_folder(unlabelled)
            assert scene.num_frames == 8 and scene.num_labelled_frames == 0
            yield Service(live, client, labelled.name, unlabelled.name)
    finally:
        live.stop()


def wait_until(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_cancel_stops_a_pretraining_inside_its_epoch_loop(service: Service) -> None:
    """Without a per-epoch check the cancel would wait for all 5000 epochs."""
    c = service.client
    job = c.pretrain([service.labelled], epochs=5000, batch_size=4, name="long", make_current=False)
    # The message comes from the core's callback: the job is inside train_segmentation.
    wait_until(
        lambda: c.job(job.id).message.startswith("epoch "), 120, "the job to report an epoch"
    )
    c.cancel_job(job.id)
    final = c.wait_job(job.id, timeout=120, raise_on_failure=False)
    assert final.status == "cancelled" and final.result is None
    assert final.progress < 0.5  # 0.1 + 0.85 * epochs done / 5000
    assert "long" not in {m.name for m in c.models()}
    lines = [line.message for line in c.job_log(job.id, tail=1000)]
    assert not any("epoch 5000/5000" in line for line in lines)


@needs_adapt
def test_adapt_on_a_scene_without_ground_truth(service: Service) -> None:
    c = service.client
    base = c.wait_job(
        c.pretrain([service.labelled], epochs=1, batch_size=4, name="base").id, timeout=300
    )
    assert base.status == "succeeded", base.error
    seen: list[float] = []
    done = c.wait_job(
        c.adapt(service.unlabelled, model="base", preset="tiny").id,
        timeout=600,
        on_progress=lambda j: seen.append(j.progress),
    )
    assert done.status == "succeeded", done.error
    assert seen == sorted(seen) and seen[-1] == 1.0
    new = c.model(done.result["model_id"])
    assert (
        new.parent_id == base.result["model_id"]
        and new.lineage == "base"
        and new.name == "base-step1"
    )
    assert new.adapted_scene == service.unlabelled and new.size_bytes > 0
    # Nothing to score against: the metrics that need ground truth are withheld, not made up.
    assert new.metrics["val_miou"] is None and new.metrics["before_val_miou"] is None
    assert new.metrics["pseudo_label_miou"] is None and new.metrics["prediction_miou"] is None
    entry = c.scene_nerf(service.unlabelled)
    assert entry.job_id == done.id and entry.labels_source == "adapt:base" and entry.size_bytes > 0
    assert c.scene(service.unlabelled).has_nerf
    assert service.unlabelled in {e.scene for e in c.memory().entries}
    m = c.continual_metrics(lineage="base")
    assert [s.model_id for s in m.steps] == [new.id] and m.acc is None
