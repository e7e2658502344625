"""The README's main job, end to end on tiny settings."""

from __future__ import annotations

import json
import math

from csa_core.cli.main import main


def test_demo_writes_scenes_previews_and_label_fusion(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main([
        "demo", "--out", str(out), "--frames", "10", "--size", "48x36",
        "--pretrain-scenes", "1", "--target-scenes", "1",
        "--seven-scenes", str(tmp_path / "absent"),
        "--fusion-size", "48x36", "--fusion-steps", "60",
    ])  # fmt: skip
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert set(report["scenes"]) == {"apartment_0_0", "office_1000_0"}
    assert report["scenes"]["office_1000_0"]["frames"] == 10
    assert len(report["scenes"]["office_1000_0"]["classes"]) >= 3
    assert sorted(p.name for p in (out / "previews" / "apartment_0_0").iterdir()) == ["0.png"]
    fusion = report["label_fusion"]
    assert fusion["scene"] == "office_1000_0" and fusion["train_views"] == 8
    assert 0.0 < fusion["noisy_miou"] < 1.0 and math.isfinite(fusion["fused_miou"])
    assert (out / "fusion" / "office_1000_0.nerf.safetensors").stat().st_size == fusion["checkpoint_bytes"]
    printed = " ".join(capsys.readouterr().out.split())  # rich wraps lines at the terminal width
    assert "not found: skipping the real-data import" in printed
    assert "label fusion on office_1000_0" in printed
