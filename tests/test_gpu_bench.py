"""``benchmarks/gpu_bench.py --smoke``: every stage of the GPU benchmark runs, at tiny sizes on
the CPU, and reports what it measured."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_bench.py"


def _bench():
    spec = importlib.util.spec_from_file_location("gpu_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_every_stage_runs_in_smoke_mode(tmp_path, capsys):
    bench = _bench()
    rows = bench.main(
        ["--smoke", "--threads", "1", "--json", str(tmp_path / "rows.json"),
         "--compare", "field.mlp_dtype=bfloat16"]
    )  # fmt: skip
    failed = [r for r in rows if r["what"] == "FAILED"]
    assert failed == []
    stages = {r["stage"] for r in rows}
    assert {"reference", "fast", "render", "map", "demo"} <= stages
    assert "reference [field.mlp_dtype=bfloat16]" in stages
    by = {(r["stage"], r["what"]): r["value"] for r in rows}
    # Every time is a positive finite number; samples per second follow from the steps.
    for key in [
        ("reference", "training step"),
        ("fast", "whole fit"),
        ("render", "fast: colour + labels, no depth"),
        ("render", "reference: labels of a view with depth"),
        ("map", "ray-cast read-back"),
        ("demo", "csa demo end to end"),
    ]:
        assert math.isfinite(by[key]) and by[key] > 0, key
    assert by[("reference", "paper budget (5000 steps)")] == pytest.approx(
        5000 * by[("reference", "training step")]
    )
    assert 0 <= by[("render", "fast: mIoU of those labels")] <= 100
    assert (tmp_path / "rows.json").is_file()
    out = capsys.readouterr().out
    assert "| stage | what | value | unit | note |" in out
    assert "hash encoding on cpu:" in out


def test_unknown_stages_are_refused(capsys):
    bench = _bench()
    with pytest.raises(SystemExit):
        bench.parse_args(["--stages", "reference,warp"])
    assert "unknown warp" in capsys.readouterr().err
