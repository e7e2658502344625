"""The service runs the method the experiments measure: ``csa adapt`` over two scenes and two
adapt jobs through the REST API, from the same pre-trained network with the same pre-training
scenes, seed and thread count, end with bit-identical networks and the same scores.

Two steps, so the second replays the first scene's NeRF (read back from the folder memory
bank in one case, from the artifact store in the other) and pools BatchNorm statistics that
the service carried from one job to the next as a file of the model version.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from server import capabilities
from tests.server.conftest import SCENE_SIZE, LiveServer, start_server, test_settings

pytestmark = pytest.mark.skipif(
    not all(capabilities.available(c) for c in ("seg", "nerf", "adapt")),
    reason="needs csa_core.seg, csa_core.nerf and csa_core.adapt",
)


@dataclass
class Runs:
    live: LiveServer
    pretrain_scene: Path
    scenes: list[Path]
    service_models: list  # the lineage's versions after each adapt job
    service_metrics: object  # the lineage's R matrix and scores
    service_weights: dict[str, torch.Tensor]
    base: Path  # the pre-trained network both started from
    cli_out: Path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Iterator[Runs]:
    from csa_core.cli.main import main
    from csa_core.data.synth import synthesize
    from csa_core.seg.checkpoint import load_checkpoint

    data = tmp_path_factory.mktemp("equivalence")
    # PNG frames: the service stores the uploaded bytes, so both sides decode the same pixels.
    (pre,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="apartment", seed=1
    )
    targets = [
        synthesize(data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=s)[0]
        for s in (2, 3)
    ]
    assert targets[0].name != targets[1].name
    live = start_server(test_settings(data / "service"))  # torch_threads=1, device cpu
    try:
        with live.client() as c:
            deadline = time.monotonic() + 10
            while c.health().workers_alive < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            for folder in (pre, *targets):
                c.upload_scene_folder(folder)
            base = c.wait_job(
                c.pretrain([pre.name], epochs=1, batch_size=4, name="base").id, timeout=300
            )
            assert base.status == "succeeded", base.error
            network = c.download_model("base", data / "base.safetensors")
            models = []
            for folder in targets:
                done = c.wait_job(c.adapt(folder.name, model="base", preset="tiny").id, timeout=600)
                assert done.status == "succeeded", done.error
                models.append(c.model(done.result["model_id"]))
            metrics = c.continual_metrics(lineage="base")
            final = c.download_model(models[-1].id, data / "service.safetensors")
        service_net, _ = load_checkpoint(final)

        # The same step on the command line, in this process (one torch thread, as the
        # worker: tests/conftest.py and test_settings).
        out = data / "cli"
        argv = ["adapt", *map(str, targets), "--model", str(network), "--pretrain-scenes", str(pre)]
        argv += [
            "--out",
            str(out),
            "--preset",
            "tiny",
            "--seed",
            "0",
            "--device",
            "cpu",
            "--threads",
            "1",
        ]
        assert main(argv) == 0
        yield Runs(
            live, pre, targets, models, metrics, dict(service_net.state_dict()), network, out
        )
    finally:
        live.stop()


def test_the_networks_are_bit_identical(runs: Runs) -> None:
    from csa_core.seg.checkpoint import load_checkpoint

    cli_net, _ = load_checkpoint(runs.cli_out / "model.safetensors")
    cli = cli_net.state_dict()
    assert cli.keys() == runs.service_weights.keys()
    different = [k for k, t in cli.items() if not torch.equal(t, runs.service_weights[k])]
    assert different == []
    # BatchNorm statistics included: the service pooled them over both scenes as well.
    assert any(k.endswith("running_var") for k in cli)
    base, _ = load_checkpoint(runs.base)
    changed = [
        k
        for k, t in base.state_dict().items()
        if t.is_floating_point() and not torch.equal(t, cli[k])
    ]
    assert len(changed) > len(cli) // 2  # both adapted the network, weights and statistics


def test_the_scores_are_the_same(runs: Runs) -> None:
    doc = json.loads((runs.cli_out / "results.json").read_text())
    R, b, m = doc["R"], doc["b"], runs.service_metrics
    assert [s.scene for s in m.steps] == [p.name for p in runs.scenes] == doc["scenes"]
    assert m.missing == []
    # The service scores what each step makes computable; the command line fills all of R.
    assert m.R == R and m.b == b
    for key in ("acc", "a", "fwt", "bwt"):
        assert getattr(m, key) == doc["metrics"][key], key
    for version, step in zip(runs.service_models, doc["steps"], strict=True):
        assert version.metrics["val_miou"] == step["R_row"][step["step"]]
        assert version.metrics["pseudo_label_miou"] == step["pseudo_label_miou"]
        assert version.metrics["prediction_miou"] == step["prediction_miou"]


def test_the_service_replayed_and_pooled_like_the_command_line(runs: Runs) -> None:
    from csa_core.adapt.bn_memory import BatchNormMemory
    from server.db.models import ModelVersion
    from server.db.session import session_scope
    from server.registry import BATCHNORM_FILE

    doc = json.loads((runs.cli_out / "results.json").read_text())
    first, second = (p.name for p in runs.scenes)
    assert [s["replay"] for s in doc["steps"]] == [
        {},
        {first: doc["config"]["replay"]["buffer_size"]},
    ]
    services = runs.live.services
    with session_scope(services.sessions) as s:
        versions = [s.get(ModelVersion, v.id) for v in runs.service_models]
        steps = [v.meta["step"] for v in versions]
        files = [dict(v.files) for v in versions]
    assert [st["replay"] for st in steps] == [st["replay"] for st in doc["steps"]]
    assert [st["decisions"] for st in steps] == [st["decisions"] for st in doc["steps"]]
    memories = [
        BatchNormMemory.load(services.store.open_verified(f[BATCHNORM_FILE])) for f in files
    ]
    assert [list(mem.scenes) for mem in memories] == [[first], [first, second]]
    assert [st["batchnorm_pooled"] for st in steps] == [[first], [first, second]]
