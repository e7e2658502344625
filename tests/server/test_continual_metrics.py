"""The R matrix over a lineage's adaptation history, as adapt and evaluate jobs record it."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from client import CSAClient, NotFound
from csa_core.eval import continual_metrics
from server.db.models import Evaluation, Scene
from server.registry import register_checkpoint

# mIoU[model][scene]: root = pre-trained (the b row), then one version per adapted scene.
SCORES = {
    "root": {"s0": 0.30, "s1": 0.25, "s2": 0.20},
    "step0": {"s0": 0.50, "s1": 0.28},
    "step1": {"s0": 0.45, "s1": 0.52, "s2": 0.26},
    "step2": {"s0": 0.44, "s1": 0.49, "s2": 0.55},
}


@pytest.fixture(scope="module")
def lineage(api_server, tmp_path_factory) -> str:
    """A lineage root -> step0 (scene s0) -> step1 (s1) -> step2 (s2), with evaluations."""
    services = api_server.services
    blob = Path(tmp_path_factory.mktemp("ckpt")) / "model.safetensors"
    with services.sessions() as s:
        scenes = {}
        for name in ("s0", "s1", "s2"):
            row = Scene(name=f"cm-{name}")
            s.add(row)
            s.flush()
            scenes[name] = row.id
        parent = None
        for i, model_name in enumerate(SCORES):
            blob.write_bytes(f"weights of {model_name}".encode())
            adapted = None if model_name == "root" else scenes[f"s{i - 1}"]
            m = register_checkpoint(
                s,
                services.store,
                blob,
                name=f"cm-{model_name}",
                lineage="cm",
                arch="test",
                parent_id=parent,
                adapted_scene_id=adapted,
                make_current=False,
            )
            for scene_name, miou in SCORES[model_name].items():
                s.add(
                    Evaluation(
                        model_version_id=m.id, scene_id=scenes[scene_name], split="val", miou=miou
                    )
                )
            parent = m.id
        s.commit()
    return "cm"


def test_r_matrix_and_scores_match_the_core_metrics(client: CSAClient, lineage: str) -> None:
    m = client.continual_metrics(lineage=lineage)
    assert [s.scene for s in m.steps] == ["cm-s0", "cm-s1", "cm-s2"]
    assert [s.model for s in m.steps] == ["cm-step0", "cm-step1", "cm-step2"]
    assert m.b == [0.30, 0.25, 0.20]
    assert m.R == [[0.50, 0.28, None], [0.45, 0.52, 0.26], [0.44, 0.49, 0.55]]
    assert m.missing == []
    nan = float("nan")
    want = continual_metrics(
        [[0.50, 0.28, nan], [0.45, 0.52, 0.26], [0.44, 0.49, 0.55]], [0.30, 0.25, 0.20]
    )
    for key in ("acc", "a", "fwt", "bwt"):
        assert math.isclose(getattr(m, key), want[key])
    assert math.isclose(m.bwt, ((0.44 - 0.50) + (0.49 - 0.52)) / 2)


def test_missing_entries_are_named_and_scores_withheld(client: CSAClient, lineage: str) -> None:
    m = client.continual_metrics(lineage=lineage, split="train")
    assert m.acc is None and "R[0][0]" in m.missing and "b[2]" in m.missing


def test_unknown_lineage_is_404(client: CSAClient) -> None:
    with pytest.raises(NotFound):
        client.continual_metrics(lineage="no-such-lineage")


def test_models_show_their_lineage(client: CSAClient, lineage: str) -> None:
    models = {m.name: m for m in client.models(lineage=lineage)}
    assert models["cm-step1"].parent_id == models["cm-step0"].id
    assert models["cm-step0"].children == [models["cm-step1"].id]
    assert models["cm-step2"].adapted_scene == "cm-s2"
    assert models["cm-step2"].evaluations == {
        "cm-s0/val": 0.44,
        "cm-s1/val": 0.49,
        "cm-s2/val": 0.55,
    }
    assert client.set_current_model("cm-step2").is_current
    assert client.model("current").name == "cm-step2"
