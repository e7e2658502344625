"""``csa experiment``: each experiment end to end on two tiny rooms, and its files' content."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from csa_core.errors import CSAInputError
from csa_core.experiments.report import ExperimentReport, write_report
from tests.experiments.conftest import csa


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def experiment_entry(out: Path, name: str) -> dict:
    doc = json.loads((out / "config.json").read_text())
    return doc["experiments"][name]


def assert_png(path: Path) -> None:
    img = cv2.imread(str(path))
    assert img is not None and img.size > 0 and img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 0  # not a blank canvas


def common(workspace, out: Path, name: str, *extra: str) -> list[str]:
    return [
        "experiment",
        name,
        "--model",
        workspace.model,
        "--scenes",
        *workspace.scenes,
        "--out",
        out,
        "--preset",
        "tiny",
        "--device",
        "cpu",
        *extra,
    ]


def test_pseudo_labels_two_seeds(workspace, tmp_path, capsys):
    code, stdout, _ = csa(capsys, *common(workspace, tmp_path, "pseudo-labels", "--seeds", "0,1"))
    assert code == 0
    rows = read_csv(tmp_path / "pseudo-labels.csv")
    assert len(rows) == 2 * 3  # scenes x label sources
    assert {r["labels"] for r in rows} == {"network", "mapping", "nerf"}
    for r in rows:
        assert r["seeds"] == "2"
        assert 0.0 <= float(r["miou_mean"]) <= 1.0 and math.isfinite(float(r["miou_std"]))
        if r["labels"] != "nerf":  # only the NeRF fit depends on the seed
            assert float(r["miou_std"]) == 0.0
    md = (tmp_path / "pseudo-labels.md").read_text()
    assert md.strip() in stdout and "± " in md and "office_1" in md and "**mean**" in md
    entry = experiment_entry(tmp_path, "pseudo-labels")
    assert entry["seeds"] == [0, 1]
    assert len(entry["runs"]) == 4 and {r["seed"] for r in entry["runs"]} == {0, 1}
    assert entry["runs"][1]["config"]["nerf"]["seed"] == 0
    assert entry["runs"][3]["config"]["nerf"]["seed"] == 1
    assert entry["versions"]["torch"] and entry["inputs"]["preset"] == "tiny"


def test_one_step_per_scene_and_method(workspace, tmp_path, capsys):
    methods = ["gi_nl", "mapping", "cotta"]
    code, stdout, _ = csa(
        capsys,
        *common(workspace, tmp_path, "one-step", "--seeds", "0", "--methods", ",".join(methods)),
    )
    assert code == 0
    rows = read_csv(tmp_path / "one-step.csv")
    assert len(rows) == 2 * len(methods)
    assert [r["method"] for r in rows[:3]] == methods
    for scene in ("office_0", "office_1"):
        befores = {r["before"] for r in rows if r["scene"] == scene}
        assert len(befores) == 1  # the pre-trained network, the same for every method
    for r in rows:
        assert float(r["after_std"]) == 0.0 and r["seeds"] == "1"
        after, before = float(r["after_mean"]), float(r["before"])
        assert 0.0 <= after <= 1.0
        assert float(r["gain_mean"]) == pytest.approx(after - before)
    entry = experiment_entry(tmp_path, "one-step")
    assert entry["seeds"] == [0] and len(entry["runs"]) == 6
    gi_nl = next(r for r in entry["runs"] if r["method"] == "gi_nl")
    assert gi_nl["config"]["mode"] == "gi_nl" and gi_nl["memory_bytes"]["nerf_total"] > 0
    cotta = next(r for r in entry["runs"] if r["method"] == "cotta")
    assert cotta["method_settings"]["scales"] == [1.0] and cotta["method_settings"]["flip"]
    assert "| office_0 | GI+NL (ours) |" in stdout and "wrote" in stdout


def test_multi_step_fills_r_for_every_method(workspace, tmp_path, capsys):
    methods = ["ours", "mapping", "cotta"]
    code, stdout, _ = csa(
        capsys,
        *common(
            workspace, tmp_path, "multi-step", "--methods", ",".join(methods), "--mode", "gi_nl"
        ),
    )
    assert code == 0
    rows = read_csv(tmp_path / "multi-step.csv")
    assert len(rows) == 2 * len(methods)  # steps x methods
    entry = experiment_entry(tmp_path, "multi-step")
    assert entry["seeds"] == [0] and [r["method"] for r in entry["runs"]] == methods
    for run in entry["runs"]:
        R = np.array(run["R"], dtype=float)
        assert R.shape == (2, 2) and np.isfinite(R).all()
        mine = [r for r in rows if r["method"] == run["method"]]
        assert [float(r["adapt_mean"]) for r in mine] == pytest.approx(np.diagonal(R))
        assert mine[0]["previous_mean"] == "" and float(mine[1]["previous_mean"]) == pytest.approx(
            R[1, 0]
        )
        results = json.loads(Path(run["results"]).read_text())
        assert results["config"]["method"] == run["method"] and results["config"]["mode"] == "gi_nl"
        assert np.allclose(np.array(results["R"], dtype=float), R)
    metrics = read_csv(tmp_path / "multi-step-metrics.csv")
    assert [m["method"] for m in metrics] == methods
    assert all(math.isfinite(float(m["acc_mean"])) and m["acc_std"] == "0.0" for m in metrics)
    assert_png(tmp_path / "multi-step.png")
    for label in ("| CSA (ours) | Adapt |", "| Mapping | Previous |", "| CoTTA | Adapt |", "BWT"):
        assert label in stdout


def test_multi_step_runs_every_method_with_and_without_adabn(workspace, tmp_path, capsys):
    methods = ["cotta", "finetune"]
    argv = common(workspace, tmp_path, "multi-step", "--methods", ",".join(methods))
    code, stdout, _ = csa(capsys, *argv, "--adabn", "both")
    assert code == 0
    entry = experiment_entry(tmp_path, "multi-step")
    assert entry["inputs"]["adabn"] == "both"
    assert [(r["method"], r["adabn"]) for r in entry["runs"]] == [
        (m, a) for m in methods for a in (True, False)
    ]
    for run in entry["runs"]:
        results = json.loads(Path(run["results"]).read_text())
        assert results["config"]["adabn"] is run["adabn"]
        assert Path(run["results"]).parent.name == "seed0"
        assert Path(run["results"]).parent.parent.name == f"adabn-{'on' if run['adabn'] else 'off'}"
        # BatchNorm statistics are pooled only where AdaBN re-estimated them.
        pooled = [s["batchnorm_pooled"] for s in results["steps"]]
        assert pooled == (
            [["office_0"], ["office_0", "office_1"]] if run["adabn"] else [None, None]
        )
    for method in methods:
        on, off = (
            np.array(
                next(r for r in entry["runs"] if (r["method"], r["adabn"]) == (method, a))["R"]
            )
            for a in (True, False)
        )
        assert not np.allclose(on, off)  # AdaBN changes every method's scores, CoTTA's too
    rows = read_csv(tmp_path / "multi-step.csv")
    assert [(r["method"], r["adabn"]) for r in rows[::2]] == [
        (m, a) for m in methods for a in ("on", "off")
    ]
    metrics = read_csv(tmp_path / "multi-step-metrics.csv")
    assert [(m["method"], m["adabn"]) for m in metrics] == [
        (m, a) for m in methods for a in ("on", "off")
    ]
    for label in (
        "| CoTTA, with AdaBN | Adapt |",
        "| CoTTA, without AdaBN | Previous |",
        "| fine-tune (no replay), without AdaBN | Adapt |",
    ):
        assert label in stdout


def test_footprint_per_method_and_scene_count(workspace, tmp_path, capsys):
    code, stdout, _ = csa(
        capsys, *common(workspace, tmp_path, "footprint", "--pretrain-scenes", workspace.pretrain)
    )
    assert code == 0
    rows = read_csv(tmp_path / "footprint.csv")
    kinds = [
        "nerf_fp16",
        "nerf_fp32",
        "mapping_raw",
        "mapping_png",
        "cotta",
        "replay_buffer",
        "pretrain_replay",
    ]
    assert len(rows) == 2 * len(kinds)
    size = {(r["stored"], int(r["scenes"])): float(r["bytes_mean"]) for r in rows}
    assert all(float(r["bytes_std"]) == 0.0 for r in rows)
    for kind in ("nerf_fp16", "nerf_fp32", "mapping_raw"):
        assert size[(kind, 2)] > size[(kind, 1)] > 0  # grows with every scene
    assert size[("nerf_fp16", 1)] < 0.6 * size[("nerf_fp32", 1)]
    assert size[("cotta", 1)] == size[("cotta", 2)] > size[("nerf_fp16", 2)]  # constant
    assert size[("pretrain_replay", 1)] > 0
    assert_png(tmp_path / "footprint.png")
    assert experiment_entry(tmp_path, "footprint")["seeds"] == [0]
    assert "CoTTA: teacher + source copies" in stdout


def test_nerf_checkpoint_size_does_not_depend_on_training(workspace):
    """The footprint experiment builds NeRFs without fitting them: that is exact only if a
    checkpoint's size is the same before and after training."""
    from csa_core.adapt.config import preset
    from csa_core.adapt.pseudo_labels import nerf_config
    from csa_core.data.scene_io import read_scene
    from csa_core.nerf.checkpoint import checkpoint_bytes
    from csa_core.nerf.fit import fit_semantic_nerf

    scene = read_scene(workspace.scenes[0])
    cfg = nerf_config(preset("tiny").nerf)
    sizes = {
        steps: len(
            checkpoint_bytes(fit_semantic_nerf(scene, config=cfg, steps=steps, progress=False)[0])
        )
        for steps in (0, 20)
    }
    assert sizes[0] == sizes[20]


def test_experiments_share_one_config_file(tmp_path):
    def report(name: str) -> ExperimentReport:
        return ExperimentReport(name, "| a |\n|---|\n| 1 |", ["a"], [[1.0], [float("nan")]])

    write_report(report("one"), tmp_path, {"seeds": [0]}, {"csa": "x"})
    write_report(report("two"), tmp_path, {"seeds": [1, 2]}, {"csa": "x"})
    doc = json.loads((tmp_path / "config.json").read_text())
    assert doc["experiments"]["one"]["seeds"] == [0] and doc["experiments"]["two"]["seeds"] == [
        1,
        2,
    ]
    assert [r["a"] for r in read_csv(tmp_path / "one.csv")] == ["1.0", ""]  # NaN: empty cell
    (tmp_path / "config.json").write_text('{"something": "else"}')
    with pytest.raises(CSAInputError, match="not written by csa experiment"):
        write_report(report("three"), tmp_path, {}, {})


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"--model": "{tmp}/missing.safetensors"},
            "missing.safetensors: checkpoint file not found",
        ),
        ({"--scenes": "{unlabelled}"}, "label-nyu40: ground truth needed to score this scene"),
        ({"--methods": "gi_nl,magic"}, "--methods: unknown method 'magic'"),
        ({"--seeds": "0,x"}, "--seeds: expected integers"),
        ({"--preset": "huge"}, "--preset: unknown preset 'huge'"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(workspace, tmp_path, capsys, change, message):
    values = {
        "--model": str(workspace.model),
        "--scenes": str(workspace.scenes[0]),
        "--methods": "gi_nl",
        "--seeds": "0",
        "--preset": "tiny",
    }
    for key, value in change.items():
        values[key] = value.format(tmp=tmp_path, unlabelled=workspace.unlabelled)
    argv = ["experiment", "one-step", "--out", str(tmp_path / "out")]
    for key, value in values.items():
        argv += [key, value]
    code, stdout, stderr = csa(capsys, *argv)
    assert code == 2 and stdout == ""
    assert stderr.startswith("csa: error: ") and message in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_multi_step_resume_reuses_finished_runs_and_redoes_changed_ones(
    workspace, tmp_path, capsys, monkeypatch
):
    """``--resume``: runs an earlier invocation finished with the same inputs are read back,
    not run again, and the table is the same; a run whose config changed, or one that never
    finished, is done again."""
    import csa_core.experiments.multi_step as multi_step

    argv = common(workspace, tmp_path, "multi-step", "--methods", "finetune", "--seeds", "0,1")
    code, first, _ = csa(capsys, *argv)
    assert code == 0
    ran: list[tuple[str, int]] = []
    real = multi_step.run_continual

    def counting(model, scenes, config, out, *args, **kwargs):
        ran.append((kwargs["method"], config.seg.seed))
        return real(model, scenes, config, out, *args, **kwargs)

    monkeypatch.setattr(multi_step, "run_continual", counting)
    # Seed 1's run "stopped" before its end: its record has no metrics yet.
    seed1 = tmp_path / "runs" / "multi-step" / "finetune" / "adabn-on" / "seed1" / "results.json"
    record = json.loads(seed1.read_text())
    record["metrics"] = {}
    seed1.write_text(json.dumps(record))
    code, again, _ = csa(capsys, *argv, "--resume")
    assert code == 0 and ran == [("finetune", 1)]  # seed 0 reused, seed 1 redone
    assert again.split("wrote")[0] == first.split("wrote")[0]  # the same table

    ran.clear()
    code, _, _ = csa(capsys, *argv, "--resume", "--set", "seg.lr=3e-5")
    assert code == 0 and ran == [("finetune", 0), ("finetune", 1)]  # another config: both again
    ran.clear()
    code, _, _ = csa(capsys, *argv)  # without --resume every run is done again
    assert code == 0 and len(ran) == 2


def test_resume_accepts_a_record_from_before_a_field_was_added_only_at_its_default(tmp_path):
    """A run recorded before a config field existed still matches if the field is at its
    default now; at another value it does not; a changed field never matches."""
    from types import SimpleNamespace

    from csa_core.adapt.config import cpu
    from csa_core.experiments.inputs import ExperimentInputs

    config = cpu()
    record_config = {
        **json.loads(json.dumps(config.to_dict())),
        "method": "finetune",
        "pretrain_scenes": [],
    }
    del record_config["nerf"]["joint_prefit_epochs"]  # "recorded before the field existed"
    parts = ("multi-step", "finetune", "adabn-on", "seed0")
    folder = tmp_path.joinpath("runs", *parts)
    folder.mkdir(parents=True)
    b = np.array([0.25, 0.5])
    record = {
        "scenes": ["a", "b"],
        "R": [[0.3, None], [0.2, 0.6]],
        "b": b.tolist(),
        "metrics": {"acc": 0.4},
        "config": record_config,
    }
    (folder / "results.json").write_text(json.dumps(record))
    inputs = SimpleNamespace(
        resume=True,
        out=tmp_path,
        scenes=[SimpleNamespace(name="a"), SimpleNamespace(name="b")],
        pretrain_scenes=[],
    )
    found = ExperimentInputs.finished_run(inputs, parts, config, "finetune", b)
    assert found is not None and np.isnan(found.R[0, 1]) and found.metrics == {"acc": 0.4}
    assert ExperimentInputs.finished_run(inputs, parts, config, "mapping", b) is None
    assert ExperimentInputs.finished_run(inputs, parts, config, "finetune", b + 0.01) is None
    changed = cpu()
    changed.nerf.joint_prefit_epochs = 2.0
    assert ExperimentInputs.finished_run(inputs, parts, changed, "finetune", b) is None
    changed = cpu()
    changed.seg.lr = 1e-3
    assert ExperimentInputs.finished_run(inputs, parts, changed, "finetune", b) is None
