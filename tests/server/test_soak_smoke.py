"""``benchmarks/soak.py --smoke``: a real ``csa serve`` on loopback (SQLite) under about 20 s of
mixed traffic from 8 clients answers every request, none with a 5xx, and the report holds the
latency percentiles of every route the clients use, the server's RSS over time and its memory
summary (RSS at the start and end of the traffic, the peak)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from server import capabilities

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "soak.py"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not capabilities.available("nerf"), reason="the setup fits a NeRF"),
]

ROUTES = {
    "POST /scenes",
    "POST /scenes/{scene}/frames",
    "POST /predict",
    "POST /scenes/{scene}/render",
    "POST /jobs",
    "GET /scenes",
    "GET /scenes/{scene}",
    "GET /scenes/{scene}/frames",
    "GET /jobs",
    "GET /models",
    "GET /memory",
}


def _bench():
    spec = importlib.util.spec_from_file_location("soak", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while it loads
    spec.loader.exec_module(module)
    return module


def test_soak_smoke_mode_answers_every_request_without_a_server_error(tmp_path, capsys) -> None:
    bench = _bench()
    out = tmp_path / "soak.json"
    results = bench.main(["--smoke", "--sqlite", "--json", str(out)])
    printed = capsys.readouterr().out
    assert bench.exit_code(results) == 0, printed
    assert results["server_errors"] == 0 and results["unanswered"] == 0 and results["server_alive"]
    assert json.loads(out.read_text())["requests"] == results["requests"]
    rows = {r["route"]: r for r in results["routes"]}
    assert set(rows) == ROUTES, printed  # every kind of traffic ran (POST /jobs once per operator)
    for route, row in rows.items():
        assert row["requests"] == sum(row["statuses"].values()), route
        assert 0 < row["p50_ms"] <= row["p95_ms"] <= row["p99_ms"], route
        assert route in printed
    # The work the clients asked for was done, not refused: uploads stored, views rendered.
    assert rows["POST /scenes/{scene}/frames"]["statuses"].get("201", 0) > 0
    assert rows["POST /scenes/{scene}/render"]["statuses"].get("200", 0) > 0
    assert rows["POST /predict"]["statuses"].get("200", 0) > 0
    assert rows["POST /jobs"]["statuses"].get("202", 0) > 0
    rss = results["rss_mib"]
    assert len(rss) >= 5 and all(mib > 50 for _, mib in rss)  # a Python with torch, sampled
    assert "server RSS (MiB) over time" in printed and "p99 ms" in printed
    # RSS when the server was up, at the traffic's start and end, and the peak (VmHWM).
    memory = results["memory"]
    assert 50 < memory["up_mib"] and 50 < memory["traffic_start_mib"] <= memory["peak_mib"]
    assert 50 < memory["end_mib"] <= memory["peak_mib"]
    assert memory["sampled_max_mib"] <= memory["peak_mib"]
    assert memory["growth_mib"] == memory["end_mib"] - memory["traffic_start_mib"]
    assert "server memory (MiB" in printed and "(VmHWM)" in printed


def test_the_memory_peak_is_never_below_a_sample() -> None:
    """Linux raises VmHWM lazily: a short peak the allocator gave back can leave it below a
    sample of VmRSS, and then the sample is the peak."""
    bench = _bench()
    rss = [(0.0, 100.0), (10.0, 130.5), (20.0, 120.0)]
    below = bench.memory_summary({"rss": 90.0}, {"rss": 100.0}, {"rss": 120.0, "hwm": 130.4}, rss)
    assert (below["peak_mib"], below["sampled_max_mib"]) == (130.5, 130.5)
    above = bench.memory_summary({"rss": 90.0}, {"rss": 100.0}, {"rss": 120.0, "hwm": 140.0}, rss)
    assert (above["peak_mib"], above["sampled_max_mib"]) == (140.0, 130.5)
