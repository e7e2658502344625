"""``csa adapt``: one scene is one step, several a continual run; checkpoint and results.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from csa_core.seg.checkpoint import load_checkpoint, read_model_card
from csa_core.seg.predict import evaluate_scene
from tests.experiments.conftest import csa


def test_one_scene_is_one_step_with_a_before_after_table(workspace, tmp_path, capsys):
    out = tmp_path / "one"
    argv = ["adapt", "--model", workspace.model, workspace.scenes[1], "--out", out]
    # The collapse guard is tested in tests/adapt/test_collapse.py; here it would fall back to
    # the tiny network's predictions on this room (whose thin furniture that network barely
    # labels) and bank no NeRF, which is the flow this test follows.
    code, stdout, _ = csa(
        capsys, *argv, "--preset", "tiny", "--mode", "gi_nl", "--device", "cpu",
        "--set", "collapse.enabled=false",
    )  # fmt: skip
    assert code == 0
    assert "| before |" in stdout and "| after |" in stdout and "val mIoU %" in stdout
    doc = json.loads((out / "results.json").read_text())
    assert doc["task"] == "one-step" and doc["config"]["mode"] == "gi_nl"
    assert doc["config"]["method"] == "ours" and doc["config"]["preset"] == "tiny"
    result = doc["result"]
    assert set(result["before"]) == set(result["after"]) == {"val", "train"}
    parent = read_model_card(workspace.model)
    model, card = load_checkpoint(out / "model.safetensors")
    assert card.parent == parent.weights_id and card.train_config["task"] == "one-step"
    assert card.input_size == parent.input_size
    from csa_core.data.scene_io import read_scene

    scene = read_scene(workspace.scenes[1])
    assert evaluate_scene(model, scene, "val").miou() == pytest.approx(result["after"]["val"])
    assert len(list((out / "memory").glob("*.safetensors"))) == 1  # the scene's NeRF


def test_several_scenes_are_a_continual_run(workspace, tmp_path, capsys):
    out = tmp_path / "seq"
    argv = ["adapt", "--model", workspace.model, *workspace.scenes, "--out", out]
    code, stdout, _ = csa(capsys, *argv, "--preset", "tiny", "--method", "mapping")
    assert code == 0 and "pre-trained" in stdout and "ACC" in stdout
    doc = json.loads((out / "results.json").read_text())
    R = np.array(doc["R"], dtype=float)
    assert R.shape == (2, 2) and np.isfinite(R).all()
    assert doc["config"]["method"] == "mapping" and doc["config"]["method_settings"]["voxel_size"]
    assert doc["memory_bytes"]["mapping_total"] == sum(
        doc["memory_bytes"]["mapping_per_scene"].values()
    )
    assert doc["steps"][1]["replay"] == {"office_0": doc["config"]["replay"]["buffer_size"]}
    card = read_model_card(out / "model.safetensors")
    assert card.parent == read_model_card(workspace.model).weights_id
    assert card.train_config["method"] == "mapping"
    # the same output again: refused, then replaced with --overwrite
    code, stdout, stderr = csa(capsys, *argv, "--preset", "tiny", "--method", "finetune")
    assert code == 2 and "output already exists" in stderr
    code, _, _ = csa(capsys, *argv, "--preset", "tiny", "--method", "finetune", "--overwrite")
    assert code == 0
    assert json.loads((out / "results.json").read_text())["config"]["method"] == "finetune"


def test_a_scene_without_ground_truth_adapts_without_scores(workspace, tmp_path, capsys):
    out = tmp_path / "bare"
    argv = ["adapt", "--model", workspace.model, workspace.unlabelled, "--out", out]
    code, stdout, _ = csa(capsys, *argv, "--preset", "tiny", "--method", "finetune")
    assert code == 0 and "no ground truth" in stdout
    doc = json.loads((out / "results.json").read_text())
    assert doc["result"]["before"] == {} and doc["result"]["prediction_miou"] is None
    assert (out / "model.safetensors").stat().st_size > 0


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--method", "magic"], "csa: error: --method: unknown method 'magic'"),
        (["--mode", "fast"], "csa: error: --mode: unknown mode 'fast'"),
        (["--model", "{tmp}/none.safetensors"], "none.safetensors: checkpoint file not found"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(workspace, tmp_path, capsys, extra, message):
    extra = [e.format(tmp=tmp_path) for e in extra]
    argv = ["adapt", "--model", workspace.model, workspace.scenes[0], "--out", tmp_path / "o"]
    code, stdout, stderr = csa(capsys, *argv, "--preset", "tiny", *extra)
    assert code == 2 and stdout == "" and message in stderr
    assert len(stderr.strip().splitlines()) == 1


def test_a_sequence_needs_ground_truth(workspace, tmp_path, capsys):
    argv = ["adapt", "--model", workspace.model, workspace.scenes[1], workspace.unlabelled]
    code, _, stderr = csa(capsys, *argv, "--out", tmp_path / "o", "--preset", "tiny")
    assert code == 2 and "validation views need ground-truth labels" in stderr


def test_adabn_switch_and_the_paper_networks_note(workspace, tmp_path, capsys):
    """``--adabn off`` reaches any method (CoTTA here), and ``--preset paper`` says when the
    checkpoint is not the paper's network."""
    out = tmp_path / "cotta"
    argv = ["adapt", "--model", workspace.model, workspace.scenes[0], "--out", out]
    code, _, stderr = csa(capsys, *argv, "--preset", "paper", "--method", "cotta", "--adabn", "off")
    assert code == 0
    assert "note: the paper preset's network is deeplabv3_resnet101 at 320x240" in stderr
    assert "lraspp_mobilenet_v3_large at 48x36" in stderr
    doc = json.loads((out / "results.json").read_text())
    assert doc["config"]["adabn"] is False and doc["config"]["preset"] == "paper"
    assert doc["config"]["method_settings"]["scales"] == [0.5, 0.75, 1.0, 1.25, 1.5, 1.75]
    code, _, stderr = csa(capsys, *argv, "--preset", "tiny", "--method", "cotta", "--overwrite")
    assert code == 0 and "note:" not in stderr
    assert json.loads((out / "results.json").read_text())["config"]["adabn"] is True
