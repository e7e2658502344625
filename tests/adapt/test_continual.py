"""The continual driver: R matrix, metrics, memory bank, replay and the results file."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from csa_core.adapt.continual import format_table, run_continual
from csa_core.eval.continual import continual_metrics
from csa_core.seg.predict import evaluate_scene
from tests.adapt.conftest import tiny_config


@pytest.fixture(scope="module")
def run(pretrained, target_scenes, source_scenes, tmp_path_factory):
    out = tmp_path_factory.mktemp("continual")
    model = copy.deepcopy(pretrained)
    config = tiny_config("joint")
    config.joint.rounds = 1
    result = run_continual(model, target_scenes, config, out, pretrain_scenes=source_scenes)
    return result, model, out


def test_r_matrix_is_full_and_metrics_match(run, target_scenes, pretrained):
    result, model, _ = run
    T = len(target_scenes)
    assert result.R.shape == (T, T) and np.isfinite(result.R).all()
    assert ((result.R >= 0) & (result.R <= 1)).all()
    expected_b = [evaluate_scene(pretrained, s, "val").miou() for s in target_scenes]
    assert np.allclose(result.b, expected_b)
    assert result.metrics == pytest.approx(continual_metrics(result.R, result.b))
    final = [evaluate_scene(model, s, "val").miou() for s in target_scenes]
    assert np.allclose(result.R[-1], final)  # the last row is the returned network


def test_memory_bank_and_replay_grow_step_by_step(run, target_scenes):
    result, _, out = run
    names = [s.name for s in target_scenes]
    size = tiny_config().replay.buffer_size
    assert [s["replay"] for s in result.steps] == [
        {},
        {names[0]: size},
        {names[0]: size // 2, names[1]: size // 2},
    ]
    per_scene = result.memory_bytes["nerf_per_scene"]
    assert list(per_scene) == names and all(b > 0 for b in per_scene.values())
    assert sorted(p.name for p in (out / "memory").glob("*.safetensors")) == sorted(
        f"{n}.safetensors" for n in names
    )
    assert result.memory_bytes["pretrain_replay"] > 0


def test_results_file_records_config_and_every_step(run):
    result, _, out = run
    doc = json.loads((out / "results.json").read_text())
    assert doc["scenes"] == result.scenes
    assert np.allclose(np.array(doc["R"], dtype=float), result.R)
    assert doc["config"]["mode"] == "joint" and doc["config"]["replay"]["buffer_size"] == 6
    assert doc["config"]["pretrain_scenes"] and doc["metrics"]["acc"] == pytest.approx(
        result.metrics["acc"]
    )
    assert [s["step"] for s in doc["steps"]] == [0, 1, 2]
    for step in doc["steps"]:
        assert step["decisions"] and "seconds" in step and step["nerf_bytes"] > 0
    assert (out / "model.safetensors").stat().st_size > 0
    table = format_table(result)
    assert "pre-trained" in table and "ACC" in table and result.scenes[2] in table


def test_metrics_on_a_known_matrix():
    R = np.array([[0.5, 0.2, 0.1], [0.4, 0.6, 0.3], [0.45, 0.5, 0.7]])
    b = np.array([0.3, 0.1, 0.2])
    m = continual_metrics(R, b)
    assert m["acc"] == pytest.approx((0.45 + 0.5 + 0.7) / 3)
    assert m["bwt"] == pytest.approx(((0.45 - 0.5) + (0.5 - 0.6)) / 2)
    assert m["fwt"] == pytest.approx(((0.2 - 0.1) + (0.3 - 0.2)) / 2)
