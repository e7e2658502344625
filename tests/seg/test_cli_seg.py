"""``csa seg pretrain | predict | eval`` on scene folders."""

from __future__ import annotations

import json

import numpy as np
import pytest

from csa_core.cli.main import main
from csa_core.data.scene_io import read_label_folder, read_scene, write_scene
from csa_core.seg.checkpoint import read_model_card
from tests.seg.conftest import make_pattern_scene


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    scenes = [
        write_scene(make_pattern_scene(n=10, seed=s, name=f"s{s}"), root / f"s{s}") for s in (0, 1)
    ]
    ckpt = root / "model.safetensors"
    code = main(
        [
            "seg",
            "pretrain",
            *map(str, scenes),
            "--out",
            str(ckpt),
            "--size",
            "64x48",
            "--epochs",
            "2",
            "--batch-size",
            "4",
            "--lr",
            "1e-2",
        ]
    )
    assert code == 0
    return root, scenes, ckpt


def test_pretrain_writes_a_checkpoint_with_its_recipe(workspace, capsys):
    _, scenes, ckpt = workspace
    card = read_model_card(ckpt)
    assert card.arch == "lraspp_mobilenet_v3_large" and card.input_size == [64, 48]
    assert card.train_config["epochs"] == 2 and card.train_config["train_split"] == "train"
    assert card.train_config["train_scenes"] == [str(s) for s in scenes]
    assert set(card.metrics["val_miou_per_set"]) == {"s0", "s1"}
    assert card.train_config["augment"]["hflip"] == 0.5


def test_predict_writes_a_label_folder_into_the_scene(workspace, capsys):
    _, scenes, ckpt = workspace
    assert main(["seg", "predict", str(ckpt), str(scenes[0]), "--out-labels", "pred"]) == 0
    labels = read_label_folder(scenes[0] / "pred")
    assert sorted(labels, key=int) == [str(i) for i in range(10)]
    assert all(lab.shape == (48, 64) and lab.min() >= 1 for lab in labels.values())
    scene = read_scene(scenes[0], labels="all")
    assert "pred" in scene.label_folders
    assert "pred" in capsys.readouterr().out
    # An existing folder is not replaced without --overwrite.
    assert main(["seg", "predict", str(ckpt), str(scenes[0]), "--out-labels", "pred"]) == 2
    assert "already exists" in capsys.readouterr().err


def test_predict_to_another_folder_with_adabn(workspace):
    root, scenes, ckpt = workspace
    out = root / "preds" / "s1"
    assert (
        main(
            [
                "seg",
                "predict",
                str(ckpt),
                str(scenes[1]),
                "--out",
                str(out),
                "--split",
                "val",
                "--adabn",
            ]
        )
        == 0
    )
    assert sorted(read_label_folder(out), key=int) == ["8", "9"]


def test_eval_prints_miou_per_scene_and_writes_json(workspace, capsys):
    root, scenes, ckpt = workspace
    js = root / "scores.json"
    assert main(["seg", "eval", str(ckpt), *map(str, scenes), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "mIoU" in out and "s0" in out and "s1" in out and "mean" in out
    report = json.loads(js.read_text())
    card = read_model_card(ckpt)
    for name in ("s0", "s1"):
        assert report["scenes"][name]["miou"] == pytest.approx(
            card.metrics["val_miou_per_set"][name]
        )
    assert np.isfinite(report["scenes"]["s0"]["pixel_accuracy"])


def test_bad_checkpoint_is_a_one_line_error(workspace, capsys, tmp_path):
    _, scenes, _ = workspace
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a checkpoint")
    assert main(["seg", "eval", str(bad), str(scenes[0])]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("csa: error: ") and str(bad) in err and "\n" not in err


def test_reserved_label_folder_name_is_refused(workspace, capsys):
    _, scenes, ckpt = workspace
    assert main(["seg", "predict", str(ckpt), str(scenes[0]), "--out-labels", "color"]) == 2
    assert "--out-labels" in capsys.readouterr().err
