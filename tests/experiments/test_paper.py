"""``csa experiment paper``: Tab. 1 (four label sources), the ablations and the NeRF
frameworks on two tiny rooms in one report, a rerun that skips every finished unit, Tab. 3
with its R heatmap, and the command line."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from csa_core.experiments import paper, paper_numbers
from tests.experiments.conftest import csa
from tests.experiments.test_experiments import assert_png, read_csv

TABLES = "1,ablations,framework"
# Shorter NeRF fits and one joint round than the tiny preset's: the module's runs stay short.
SHORT = (
    "--set",
    "nerf.prefit_steps=40",
    "--set",
    "nerf.semantic_steps=20",
    "--set",
    "joint.rounds=1",
)


def paper_argv(workspace, out: Path, *extra: object, scenes=None) -> list[object]:
    return [
        "experiment",
        "paper",
        *(workspace.scenes[:1] if scenes is None else scenes),
        "--model",
        workspace.model,
        "--pretrain-scenes",
        workspace.pretrain,
        "--out",
        out,
        "--preset",
        "tiny",
        "--device",
        "cpu",
        *extra,
    ]


@pytest.fixture(scope="module")
def paper_run(workspace, tmp_path_factory):
    """One invocation on one tiny room for Tab. 1, the ablations and the ``fast`` framework
    row (the ``reference`` preset's 512 samples per ray are too slow for a test)."""
    from csa_core.cli.main import main

    out = tmp_path_factory.mktemp("paper")
    argv = paper_argv(workspace, out, "--tables", TABLES, "--frameworks", "fast", *SHORT)
    assert main([str(a) for a in argv]) == 0
    return out


def test_tab1_has_the_four_label_sources_beside_the_papers_numbers(paper_run):
    md = (paper_run / "paper.md").read_text()
    assert "## Tab. 1" in md and "## Ablations" in md and "## NeRF frameworks" in md
    assert "## Tab. 3" not in md  # not asked for
    header = "| scene | Network % | Mapping % | NeRF (ours) % | Ours, joint training % |"
    assert header in md
    assert "| paper (10 ScanNet scenes) | 41.7 | 44.0 | 44.7 | 45.0 |" in md
    rows = [r for r in read_csv(paper_run / "paper.csv") if r["table"] == "tab1"]
    cells = {(r["row"], r["scene"]): r for r in rows}
    assert {r["row"] for r in rows} == set(paper.TAB1_SOURCES)
    for source in paper.TAB1_SOURCES:
        for scene in ("office_0", "mean"):
            assert 0.0 <= float(cells[(source, scene)]["mean"]) <= 1.0
        assert float(cells[(source, "mean")]["paper"]) == paper_numbers.TAB1[source]
    # Each column is the record of the one-step run that made those labels.
    entry = json.loads((paper_run / "config.json").read_text())["experiments"]["paper"]
    runs = {(r["table"], r["scene"], r["method"]): r for r in entry["runs"] if "method" in r}
    joint = runs[("one-step", "office_0", "joint")]
    assert float(cells[("joint", "office_0")]["mean"]) == pytest.approx(joint["final_label_miou"])
    gi_nl = runs[("one-step", "office_0", "gi_nl")]
    assert float(cells[("nerf", "office_0")]["mean"]) == pytest.approx(gi_nl["pseudo_label_miou"])
    assert float(cells[("network", "office_0")]["mean"]) == pytest.approx(gi_nl["prediction_miou"])
    assert entry["inputs"]["tables"] == ["1", "ablations", "framework"]


def test_ablations_run_the_two_variants_with_their_loss(paper_run):
    entry = json.loads((paper_run / "config.json").read_text())["experiments"]["paper"]
    ablations = [r for r in entry["runs"] if r["table"] == "ablations"]
    assert {(r["variant"], r["scene"]) for r in ablations} == {
        (v, "office_0") for v in paper.ABLATIONS
    }
    for r in ablations:
        assert r["method"] == "gi_nl"
        assert r["config"]["nerf"]["overrides"][-1] == paper.ABLATIONS[r["variant"]][-1]
        # The NeRF the run fitted had the variant's loss (its stored config says so).
        record = json.loads(Path(r["results"]).read_text())
        assert record["config"]["nerf"]["overrides"] == r["config"]["nerf"]["overrides"]
    rows = [r for r in read_csv(paper_run / "paper.csv") if r["table"] == "ablations"]
    assert {r["row"] for r in rows} == {"paper", *paper.ABLATIONS}
    md = (paper_run / "paper.md").read_text()
    for title in paper.ABLATION_TITLES.values():
        assert title in md


def test_framework_row_measures_the_fit(paper_run, workspace):
    import math

    from csa_core.adapt.config import preset
    from csa_core.adapt.finetune import step_nerf_budget
    from csa_core.adapt.pseudo_labels import PREDICTION_FOLDER, nerf_config
    from csa_core.data.scene_io import read_scene
    from csa_core.nerf.checkpoint import checkpoint_bytes
    from csa_core.nerf.fit import fit_semantic_nerf
    from csa_core.overrides import apply_overrides

    rows = {
        r["column"]: float(r["mean"])
        for r in read_csv(paper_run / "paper.csv")
        if r["table"] == "framework"
    }
    assert set(rows) == set(paper.FRAMEWORK_METRICS)
    assert math.isfinite(rows["val_psnr"]) and rows["val_psnr"] > 0  # MSE below 1
    assert 0.0 < rows["label_miou"] <= 1.0
    assert rows["step_seconds"] > 0 and rows["render_seconds_per_view"] > 0
    entry = json.loads((paper_run / "config.json").read_text())["experiments"]["paper"]
    (unit,) = [r for r in entry["runs"] if r["table"] == "framework"]
    assert unit["preset"] == "fast" and unit["fit_steps"] == 40  # the run's budget (--set)
    assert unit["storage_dtype"] == "float16"  # the fast preset's checkpoints
    # The checkpoint size is the fast preset's under the run's budget (it does not depend on
    # training: tests/experiments/test_experiments.py).
    config = apply_overrides(preset("tiny"), [SHORT[k] for k in range(1, len(SHORT), 2)])
    scene = read_scene(workspace.scenes[0])
    budget = dataclasses.replace(step_nerf_budget(config, scene, mode="gi_nl"), preset="fast")
    fresh = fit_semantic_nerf(scene, config=nerf_config(budget), steps=0, progress=False)[0]
    # The run fitted the network's predictions: its checkpoint names their folder.
    fresh.info.label_folder = PREDICTION_FOLDER
    assert rows["checkpoint_bytes"] == len(checkpoint_bytes(fresh))
    assert "| paper (RTX 3090) | - | - | 50 MB | 0.06 | - |" in (paper_run / "paper.md").read_text()


def test_report_files_are_written(paper_run):
    for name in ("paper-tab1.png", "paper-ablations.png"):
        assert_png(paper_run / name)
    assert (paper_run / "paper.md").stat().st_size > 0
    for folder in ("one-step", paper.ABLATIONS_FOLDER, paper.FRAMEWORK_FOLDER):
        assert list((paper_run / "runs" / folder).rglob("results.json"))


def test_a_rerun_skips_finished_units_and_redoes_a_missing_one(
    workspace, paper_run, tmp_path, capsys, monkeypatch
):
    import csa_core.experiments.one_step as one_step_module
    import csa_core.nerf.fit as fit_module

    out = tmp_path / "copy"
    shutil.copytree(paper_run, out)
    ran: list[str] = []
    real_step, real_fit = one_step_module.one_step, fit_module.fit_semantic_nerf

    def counting_step(model, scene, config, method, *args):
        ran.append(f"{scene.name}/{method}")
        return real_step(model, scene, config, method, *args)

    def counting_fit(*args, **kwargs):
        ran.append("framework fit")
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(one_step_module, "one_step", counting_step)
    monkeypatch.setattr(fit_module, "fit_semantic_nerf", counting_fit)
    argv = paper_argv(workspace, out, "--tables", TABLES, "--frameworks", "fast", *SHORT)
    first = (paper_run / "paper.md").read_text()
    code, stdout, _ = csa(capsys, *argv)
    assert code == 0 and ran == []  # every unit finished earlier: nothing runs
    assert (out / "paper.md").read_text() == first  # the same report, from the records
    entry = json.loads((out / "config.json").read_text())["experiments"]["paper"]
    assert entry["runs"] and all(r["reused"] for r in entry["runs"])

    (out / "runs" / "one-step" / "office_0" / "mapping" / "seed0" / "results.json").unlink()
    code, _, _ = csa(capsys, *argv)
    assert code == 0 and ran == ["office_0/mapping"]  # only the unit without a record


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--tables", "1,9"], "--tables: unknown table '9'"),
        (["--frameworks", "mlp"], "--frameworks: unknown NeRF preset 'mlp'"),
        (["--seeds", "0,0"], "--seeds: expected distinct integers"),
        (["--preset", "huge"], "--preset: unknown preset 'huge'"),
        (["--set", "nerf.preset_overrides=('loss.semantic_form=x',)"], "semantic_form"),
    ],
)
def test_bad_options_fail_before_any_work(workspace, tmp_path, capsys, extra, message):
    code, stdout, stderr = csa(capsys, *paper_argv(workspace, tmp_path / "out", *extra))
    assert code == 2 and stdout == "" and message in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_parsing_defaults_to_the_demo_rooms_and_every_table():
    from csa_core.cli.main import build_parser

    args = build_parser().parse_args(["experiment", "paper", "--out", "runs/paper"])
    assert args.scenes == [] and args.model is None and not args.redo
    assert args.tables.split(",") == list(paper.TABLES)
    assert args.frameworks.split(",") == list(paper.FRAMEWORKS)
    assert (args.frames, args.target_scenes, args.pretrain_rooms) == (60, 3, 16)
    args = build_parser().parse_args(
        ["experiment", "paper", "a", "b", "--out", "o", "--seeds", "0,1,2", "--preset", "paper"]
    )
    assert args.scenes == [Path("a"), Path("b")] and args.seeds == "0,1,2"


def test_without_a_model_or_pretraining_scenes_it_says_what_to_give(workspace, tmp_path, capsys):
    argv = ["experiment", "paper", *workspace.scenes, "--out", tmp_path / "o", "--preset", "tiny"]
    code, _, stderr = csa(capsys, *argv)
    assert code == 2 and "--model: give a pre-trained checkpoint" in stderr


def test_tab3_writes_the_r_heatmap_and_acc_bwt(workspace, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(paper, "TAB3_METHODS", ("finetune",))
    argv = paper_argv(workspace, tmp_path, "--tables", "3", scenes=workspace.scenes)
    code, stdout, _ = csa(capsys, *argv)
    assert code == 0
    assert "## Tab. 3" in stdout and "| fine-tune (no replay) |" in stdout
    for name in ("paper-tab3-R-finetune.png", "paper-tab3-acc-bwt.png", "paper-tab3.png"):
        assert_png(tmp_path / name)
    metrics = read_csv(tmp_path / "paper-tab3-metrics.csv")
    assert [m["method"] for m in metrics] == ["finetune"]
    # AdaBN alone, the reference row: the pre-trained network with each scene's statistics.
    from csa_core.adapt.finetune import adabn_only_scores
    from csa_core.data.scene_io import read_scene
    from csa_core.seg import load_checkpoint

    assert "| AdaBN alone (reference) |" in stdout and "AdaBN alone (the pre-trained" in stdout
    rows = [r for r in read_csv(tmp_path / "paper.csv") if r["row"] == "adabn-alone"]
    by_column = {(r["column"], r["scene"]): float(r["mean"]) for r in rows}
    net, _ = load_checkpoint(workspace.model, device="cpu")
    scenes = [read_scene(p) for p in workspace.scenes]
    want = adabn_only_scores(net, scenes, seed=0, device="cpu")
    got = [by_column[("val", scene.name)] for scene in scenes]
    assert got == pytest.approx(want, abs=1e-9)
    assert by_column[("acc", "")] == pytest.approx(float(np.mean(want)), abs=1e-9)
    # The units are the multi-step experiment's: its --resume would reuse them.
    assert (
        tmp_path / "runs" / "multi-step" / "finetune" / "adabn-on" / "seed0" / "results.json"
    ).is_file()


def test_the_demo_rooms_and_the_pretrained_network_are_made_once(tmp_path, monkeypatch):
    """Without scene folders and --model: the demo's rooms and a pre-trained network, read
    back on a rerun (no second synthesis or pre-training); other pre-training inputs train
    again."""
    import argparse

    import csa_core.cli.demo_adapt as demo_adapt
    import csa_core.data.synth as synth
    from csa_core.cli.experiment import _pretrained, _rooms

    made: list[str] = []
    real_synth, real_pretrain = synth.synthesize, demo_adapt.pretrain_network

    def counting_synth(*args, **kwargs):
        made.append("rooms")
        return real_synth(*args, **kwargs)

    def counting_pretrain(*args, **kwargs):
        made.append("pretrain")
        return real_pretrain(*args, **kwargs)

    monkeypatch.setattr(synth, "synthesize", counting_synth)
    monkeypatch.setattr(demo_adapt, "pretrain_network", counting_pretrain)
    size = (48, 36)
    rooms = _rooms(tmp_path / "scenes", "apartment", 1, 6, size, 0)
    assert [p.name for p in rooms] == ["apartment_0_0"] and made == ["rooms"]
    assert _rooms(tmp_path / "scenes", "apartment", 1, 6, size, 0) == rooms and made == ["rooms"]
    args = argparse.Namespace(
        out=tmp_path, pretrain_epochs=1, synth_seed=0, redo=False, device="cpu"
    )
    ckpt = _pretrained(args, rooms, size)
    assert ckpt == tmp_path / "pretrained.safetensors" and ckpt.is_file()
    assert made == ["rooms", "pretrain"]
    assert _pretrained(args, rooms, size) == ckpt and made == ["rooms", "pretrain"]
    args.pretrain_epochs = 2  # another pre-training: done again
    _pretrained(args, rooms, size)
    assert made == ["rooms", "pretrain", "pretrain"]
