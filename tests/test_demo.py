"""The README's main job, end to end on tiny settings."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np

from csa_core.cli.main import main


def test_demo_pretrains_adapts_and_reports(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main([
        "demo", "--out", str(out), "--frames", "10", "--size", "48x36",
        "--pretrain-scenes", "1", "--pretrain-frames", "10", "--pretrain-epochs", "1",
        "--target-scenes", "2", "--preset", "tiny",
        "--seven-scenes", str(tmp_path / "absent"),
    ])  # fmt: skip
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert set(report["scenes"]) == {"apartment_0_0", "office_1000_0", "office_1000_1"}
    assert report["scenes"]["office_1000_0"]["frames"] == 10
    assert len(report["scenes"]["office_1000_0"]["classes"]) >= 3
    assert sorted(p.name for p in (out / "previews" / "apartment_0_0").iterdir()) == ["0.png"]
    assert (out / "pretrained.safetensors").is_file()
    assert report["pretrain"]["train_images"] == 8 and report["pretrain"]["best_epoch"] == 1

    results = json.loads((out / "continual" / "results.json").read_text())
    assert results["scenes"] == ["office_1000_0", "office_1000_1"]
    R = np.array(results["R"], dtype=float)
    assert R.shape == (2, 2) and np.isfinite(R).all()
    assert len(list((out / "continual" / "memory").glob("*.safetensors"))) == 2
    summary = report["summary"]
    assert [r["scene"] for r in summary] == results["scenes"]
    for j, row in enumerate(summary):
        assert math.isclose(row["pretrained"], 100 * results["b"][j])
        assert math.isclose(row["after_all"], 100 * R[-1, j])
        assert 0.0 <= row["adabn_only"] <= 100.0
    plot = cv2.imread(str(out / "plots" / "miou_per_step.png"))
    assert plot is not None and plot.shape[0] > 100
    printed = " ".join(capsys.readouterr().out.split())  # rich wraps lines at the terminal width
    assert "not found: skipping the real-data import" in printed
    assert "ACC" in printed and "the pre-trained one on the new scenes" in printed


def test_demo_label_fusion_option(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main([
        "demo", "--out", str(out), "--frames", "10", "--size", "48x36",
        "--pretrain-scenes", "1", "--pretrain-frames", "10", "--pretrain-epochs", "1",
        "--target-scenes", "1", "--preset", "tiny", "--seven-scenes", str(tmp_path / "absent"),
        "--label-fusion", "--fusion-size", "48x36", "--fusion-steps", "60",
    ])  # fmt: skip
    assert code == 0
    fusion = json.loads((out / "report.json").read_text())["label_fusion"]
    assert fusion["scene"] == "office_1000_0" and fusion["train_views"] == 8
    assert 0.0 < fusion["noisy_miou"] < 1.0 and math.isfinite(fusion["fused_miou"])
    assert (out / "fusion" / "office_1000_0.nerf.safetensors").stat().st_size == fusion[
        "checkpoint_bytes"
    ]
    assert "label fusion on office_1000_0" in " ".join(capsys.readouterr().out.split())
