"""The paper's two other rows of ours in Tab. 3 as methods of ``csa experiment multi-step``:
"Ours (I_pre replay only)" and "Ours (novel viewpoints)", on two tiny rooms."""

from __future__ import annotations

import json

from csa_core.experiments.multi_step import DEFAULT_METHODS, TITLES
from tests.experiments.conftest import csa
from tests.experiments.test_experiments import common, experiment_entry, read_csv


def test_multi_step_runs_the_papers_replay_variants(workspace, tmp_path, capsys):
    methods = ["ours-pretrain-replay", "ours-novel-views"]
    argv = common(
        workspace,
        tmp_path,
        "multi-step",
        "--methods",
        ",".join(methods),
        "--mode",
        "gi_nl",
        "--pretrain-scenes",
        workspace.pretrain,
    )
    code, stdout, _ = csa(capsys, *argv)
    assert code == 0
    assert TITLES["ours-pretrain-replay"] in stdout and TITLES["ours-novel-views"] in stdout
    entry = experiment_entry(tmp_path, "multi-step")
    runs = {r["method"]: r for r in entry["runs"]}
    assert set(runs) == set(methods)
    # Each run records the config it ran with: the variant's replay fields over the preset's.
    assert runs["ours-pretrain-replay"]["config"]["replay"]["buffer_size"] == 0
    assert runs["ours-novel-views"]["config"]["replay"]["views"] == "novel"
    assert runs["ours-novel-views"]["config"]["replay"]["buffer_size"] == 6  # tiny's
    steps = {}
    for method, run in runs.items():
        result = json.loads(open(run["results"]).read())
        assert result["config"]["method"] == method
        assert result["config"]["replay"] == run["config"]["replay"]
        steps[method] = result["steps"]
    office_0 = steps["ours-novel-views"][0]["scene"]
    # Step 2 replays the first room's NeRF at novel views (6 pairs) in one, nothing in the other;
    # both train with the pre-training slice.
    assert steps["ours-novel-views"][1]["replay"] == {office_0: 6}
    assert steps["ours-pretrain-replay"][1]["replay"] == {}
    assert steps["ours-pretrain-replay"][1]["replay_bytes"] == 0
    for method in methods:
        assert all(s["method"] == method and s["trained"] for s in steps[method])
    rows = read_csv(tmp_path / "multi-step-metrics.csv")
    assert {r["method"] for r in rows} == set(methods)
    for r in rows:
        assert 0.0 <= float(r["acc_mean"]) <= 1.0
    # The default list stays the four methods; the variants are asked for by name.
    assert DEFAULT_METHODS == ("ours", "mapping", "cotta", "finetune")
