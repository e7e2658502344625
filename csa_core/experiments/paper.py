"""Experiment ``paper``: every table of the paper on one scene sequence, in one report.

- **Tab. 1**, pseudo-label quality on the training views: the network's predictions, Mapping's
  labels, the NeRF's rendered labels and ours after joint training. Read from the one-step
  runs of Tab. 2, which made exactly these labels: the GI+NL run's predictions and NeRF labels
  (the whole fit before the pseudo-labels), the Mapping run's labels, the joint run's labels
  after its last round (``final_label_miou``).
- **Tab. 2**, one-step adaptation: the ``one-step`` experiment's methods
  (:mod:`csa_core.experiments.one_step`).
- **Tab. 3**, multi-step (continual) adaptation: the ``multi-step`` experiment with every
  method, the paper's two variants of ours included (:mod:`csa_core.experiments.multi_step`).
- **Ablations** of the supplementary, as GI+NL one-step runs beside Tab. 2's: Semantic-NeRF's
  original semantic loss (``loss.semantic_form=semantic_nerf``) and no depth loss (w_d = 0).
- **NeRF frameworks** of the supplementary: per NeRF preset, a fit on each scene's
  predictions with the run's budget: held-out PSNR, label mIoU, checkpoint size, time per
  step and per rendered view.

Every run is one unit in ``runs/``; a rerun (``resume``, the default of ``csa experiment
paper``) reads back the units an earlier invocation finished with the same inputs
(:meth:`ExperimentInputs.finished_run`, the ``multi-step`` experiment's ``--resume``) and does
the rest. The paper's numbers beside ours are in :mod:`csa_core.experiments.paper_numbers`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Sequence

import numpy as np

from csa_core.adapt.config import AdaptConfig, nerf_config
from csa_core.adapt.continual import ContinualResult
from csa_core.adapt.finetune import adabn_only_scores, step_nerf_budget
from csa_core.adapt.pseudo_labels import (
    PREDICTION_FOLDER,
    label_miou,
    predict_frames,
    render_at_frames,
    with_labels,
)
from csa_core.atomic_io import write_text_atomic
from csa_core.data.scene import Scene
from csa_core.errors import CSAInputError
from csa_core.experiments import (
    PAPER_FRAMEWORKS,
    PAPER_TABLES,
    multi_step,
    one_step,
    paper_numbers,
)
from csa_core.experiments.inputs import ExperimentInputs
from csa_core.experiments.pseudo_labels import labelling_network
from csa_core.experiments.report import (
    Bars,
    ExperimentReport,
    Heatmap,
    Series,
    jsonable,
    markdown_table,
    mean_std,
    pct,
)

log = logging.getLogger(__name__)

NAME = "paper"
# What ``--tables`` may name, in the report's order.
TABLES: tuple[str, ...] = PAPER_TABLES
TAB1_SOURCES: tuple[str, ...] = ("network", "mapping", "nerf", "joint")
TAB1_TITLES = {
    "network": "Network",
    "mapping": "Mapping",
    "nerf": "NeRF (ours)",
    "joint": "Ours, joint training",
}
# The one-step run each Tab. 1 column is read from, and the record field.
TAB1_FROM = {
    "network": ("gi_nl", "prediction_miou"),
    "mapping": ("mapping", "pseudo_label_miou"),
    "nerf": ("gi_nl", "pseudo_label_miou"),
    "joint": ("joint", "final_label_miou"),
}
TAB2_METHODS: tuple[str, ...] = one_step.DEFAULT_METHODS
TAB3_METHODS: tuple[str, ...] = multi_step.ALLOWED_METHODS
# The ablations: GI+NL one-step runs (NeRF labels after the whole fit, then fine-tuning on
# them) with these NeRF preset overrides added; the reference row is Tab. 2's GI+NL runs.
ABLATION_METHOD = "gi_nl"
ABLATIONS: dict[str, tuple[str, ...]] = {
    "semantic-nerf-loss": ("loss.semantic_form=semantic_nerf",),
    "no-depth-loss": ("loss.depth=0",),
}
ABLATION_TITLES = {
    "paper": "paper: NLL of normalised probabilities (Eq. 3-4), w_d = 0.1",
    "semantic-nerf-loss": "Semantic-NeRF's loss: CE of composited logits",
    "no-depth-loss": "no depth loss, w_d = 0",
}
FRAMEWORKS: tuple[str, ...] = PAPER_FRAMEWORKS
# Folders of the units under ``out/runs``: Tab. 2's and Tab. 3's are the ``one-step`` and
# ``multi-step`` experiments' own, so either command can reuse the other's finished runs.
ABLATIONS_FOLDER = "paper-ablations"
FRAMEWORK_FOLDER = "paper-framework"
FRAMEWORK_METRICS: tuple[str, ...] = (
    "val_psnr",
    "label_miou",
    "checkpoint_bytes",
    "step_seconds",
    "render_seconds_per_view",
)


def check_tables(names: Sequence[str]) -> list[str]:
    """``--tables`` items in the report's order; an input error for an unknown one."""
    for name in names:
        if name not in TABLES:
            raise CSAInputError(
                "--tables", f"unknown table {name!r} (choose from {', '.join(TABLES)})"
            )
    if not names:
        raise CSAInputError("--tables", "no table given")
    return [t for t in TABLES if t in names]


def check_frameworks(names: Sequence[str]) -> list[str]:
    """``--frameworks`` items: NeRF presets (``csa_core.nerf.config.PRESETS``)."""
    from csa_core.nerf.config import PRESETS

    for name in names:
        if name not in PRESETS:
            raise CSAInputError(
                "--frameworks", f"unknown NeRF preset {name!r} (choose from {', '.join(PRESETS)})"
            )
    if not names:
        raise CSAInputError("--frameworks", "no NeRF preset given")
    return list(dict.fromkeys(names))


def one_step_methods(tables: Sequence[str]) -> list[str]:
    """The one-step methods the chosen tables read (Tab. 1's columns, Tab. 2, the ablations'
    reference row), in Tab. 2's order."""
    needed: set[str] = set()
    if "1" in tables:
        needed |= {method for method, _ in TAB1_FROM.values()}
    if "2" in tables:
        needed |= set(TAB2_METHODS)
    if "ablations" in tables:
        needed.add(ABLATION_METHOD)
    return [m for m in TAB2_METHODS if m in needed]


def ablation_config(config: AdaptConfig, items: Sequence[str]) -> AdaptConfig:
    """``config`` with NeRF config items ``items`` added after its own (checked now)."""
    nerf = dataclasses.replace(config.nerf, overrides=(*config.nerf.overrides, *items))
    return dataclasses.replace(config, nerf=nerf)


def run(
    inputs: ExperimentInputs,
    tables: Sequence[str] = TABLES,
    frameworks: Sequence[str] = FRAMEWORKS,
) -> ExperimentReport:
    """Run the units of ``tables`` (each skipped when finished earlier, with ``inputs.resume``)
    and compose the report."""
    tables = check_tables(tables)
    frameworks = check_frameworks(frameworks)
    before = one_step.scores_before(inputs)
    one_runs: list[dict] = []
    ablation_runs: list[dict] = []
    framework_runs: list[dict] = []
    methods = one_step_methods(tables)
    for seed in inputs.seeds:
        config = inputs.config(seed)
        pretrain = one_step.context(inputs, config)
        for scene in inputs.scenes:
            for method in methods:
                parts = (one_step.NAME, scene.name, method, f"seed{seed}")
                one_runs.append(
                    one_step.run_unit(
                        inputs, parts, scene, method, seed, config, before[scene.name], pretrain
                    )
                )
            if "ablations" in tables:
                for variant, items in ABLATIONS.items():
                    parts = (ABLATIONS_FOLDER, variant, scene.name, f"seed{seed}")
                    entry = one_step.run_unit(
                        inputs,
                        parts,
                        scene,
                        ABLATION_METHOD,
                        seed,
                        ablation_config(config, items),
                        before[scene.name],
                        pretrain,
                    )
                    ablation_runs.append({**entry, "variant": variant})
            if "framework" in tables:
                for name in frameworks:
                    parts = (FRAMEWORK_FOLDER, name, scene.name, f"seed{seed}")
                    framework_runs.append(
                        framework_unit(inputs, parts, scene, name, seed, config, before[scene.name])
                    )
    multi = None
    adabn: list[list[float]] = []
    if "3" in tables:
        multi = multi_step.run(dataclasses.replace(inputs, methods=list(TAB3_METHODS)))
        for seed in inputs.seeds:
            seg = inputs.config(seed).seg
            adabn.append(
                # It changes copies only, so the pre-trained network itself is safe to give.
                adabn_only_scores(inputs.model, inputs.scenes, seed=seg.seed, device=seg.device)
            )
    return compose(inputs, tables, before, one_runs, multi, ablation_runs, framework_runs, adabn)


def framework_unit(
    inputs: ExperimentInputs,
    parts: Sequence[str],
    scene: Scene,
    preset_name: str,
    seed: int,
    config: AdaptConfig,
    before: float,
) -> dict:
    """Fit a NeRF of preset ``preset_name`` (with the run's budget: the fine-tuning modes'
    fit) to ``scene``'s predictions and measure it; recorded like a one-step run (the
    measurements as its metrics) so that ``finished_run`` finds it on a rerun."""
    from csa_core.nerf.checkpoint import checkpoint_bytes
    from csa_core.nerf.fit import fit_semantic_nerf

    budget = dataclasses.replace(step_nerf_budget(config, scene, mode="gi_nl"), preset=preset_name)
    unit = dataclasses.replace(config, nerf=budget)
    method = f"nerf-{preset_name}"
    b = np.array([before], dtype=np.float64)
    result = inputs.finished_run(parts, unit, method, b, scenes=[scene])
    reused = result is not None
    if result is None:
        work = inputs.run_folder(*parts)
        device = config.seg.device
        net = labelling_network(inputs.network(), scene, config)
        predictions = predict_frames(net, scene.train_frames, device=device)
        cfg = nerf_config(budget)
        t0 = time.perf_counter()
        nerf, stats = fit_semantic_nerf(
            with_labels(scene, PREDICTION_FOLDER, predictions),
            PREDICTION_FOLDER,
            cfg,
            device=device,
            progress=False,
        )
        fit_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, labels = render_at_frames(nerf, scene.train_frames, scene.intrinsics, color=True)
        render_seconds = (time.perf_counter() - t0) / max(1, len(scene.train_frames))
        images, _ = render_at_frames(nerf, scene.val_frames, scene.intrinsics, color=True)
        mse = (
            float(
                np.mean(
                    [
                        np.mean(
                            (images[f.name].astype(np.float64) - f.color.astype(np.float64)) ** 2
                        )
                        for f in scene.val_frames
                    ]
                )
            )
            / 255.0**2
        )
        measured = {
            "val_psnr": float("inf") if mse <= 0 else -10.0 * math.log10(mse),
            "label_miou": label_miou(labels, scene),
            "prediction_miou": label_miou(predictions, scene),
            "checkpoint_bytes": float(len(checkpoint_bytes(nerf))),
            "step_seconds": cfg.optim.rays_per_step / max(stats.rays_per_second, 1e-12),
            "render_seconds_per_view": render_seconds,
        }
        record = {
            "scene": scene.name,
            "preset": preset_name,
            "fit_steps": stats.steps,
            "fit_seconds": fit_seconds,
            "storage_dtype": cfg.storage_dtype,
            **measured,
        }
        result = ContinualResult(
            scenes=[scene.name],
            R=np.array([[np.nan]]),
            b=b,
            metrics=measured,
            steps=[record],
            config={
                **unit.to_dict(),
                "method": method,
                "pretrain_scenes": [s.name for s in inputs.pretrain_scenes],
            },
            seconds=fit_seconds,
        )
        text = json.dumps(jsonable(result.to_dict()), indent=2) + "\n"
        write_text_atomic(work / "results.json", text)
    else:
        log.info("%s: finished earlier, reused", "/".join(parts))
    return {
        **result.steps[0],
        "seed": seed,
        "reused": reused,
        "results": str(inputs.out.joinpath("runs", *parts, "results.json")),
        "config": result.config,
    }


# -- the report ------------------------------------------------------------------------------


def _by(runs: Sequence[dict], *keys: str) -> dict[tuple, list[dict]]:
    """Runs grouped by the values of ``keys`` (in the order the runs came, i.e. by seed)."""
    groups: dict[tuple, list[dict]] = {}
    for r in runs:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    return groups


def _per_seed_mean(values: dict[str, list[float]]) -> list[float]:
    """Per seed, the mean over scenes of per-scene value lists (one value per seed each)."""
    lists = list(values.values())
    n = min(len(v) for v in lists) if lists else 0
    return [float(np.mean([v[k] for v in lists])) for k in range(n)]


def _paper(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _stat_cell(values: Sequence[float], n: int, signed: bool = False) -> str:
    return pct(*mean_std(values), n, signed)


def compose(
    inputs: ExperimentInputs,
    tables: Sequence[str],
    before: dict[str, float],
    one_runs: list[dict],
    multi: ExperimentReport | None,
    ablation_runs: list[dict],
    framework_runs: list[dict],
    adabn: Sequence[Sequence[float]] = (),
) -> ExperimentReport:
    """The report: one Markdown document (ours as mean ± std over seeds, the paper's
    numbers beside), its CSV tables and the PNGs. ``adabn``: per seed, AdaBN alone's
    validation mIoU per scene (:func:`~csa_core.adapt.finetune.adabn_only_scores`), Tab. 3's
    reference row."""
    n = len(inputs.seeds)
    names = [s.name for s in inputs.scenes]
    seeds = ",".join(str(s) for s in inputs.seeds)
    sections = [
        f"# The paper's tables on {len(names)} scene{'s' * (len(names) > 1)} "
        f"(preset {inputs.preset}, seeds {seeds})\n\n"
        f"Scenes: {', '.join(names)}. Ours: mean ± std over {n} seed{'s' * (n > 1)}, mIoU %. "
        "The paper's numbers (mean of 10 ScanNet scenes, docs/method.md \"Reference "
        'numbers") are for other scenes and another network: compare orderings and gaps, '
        "not values."
    ]
    report = ExperimentReport(
        name=NAME,
        markdown="",
        csv_header=["table", "row", "column", "scene", "mean", "std", "seeds", "paper"],
        csv_rows=[],
    )
    by_method = _by(one_runs, "scene", "method")
    if "1" in tables:
        sections.append(_tab1(report, names, by_method, n))
    if "2" in tables:
        sections.append(_tab2(report, names, before, by_method, n))
    if "3" in tables and multi is not None:
        sections.append(_tab3(report, inputs, multi, n, adabn))
    if "ablations" in tables:
        sections.append(_ablations(report, names, by_method, ablation_runs, n))
    if "framework" in tables:
        sections.append(_framework(report, inputs, framework_runs, n))
    report.markdown = "\n\n".join(sections)
    report.runs = [
        *({"table": "one-step", **r} for r in one_runs),
        *({"table": "ablations", **r} for r in ablation_runs),
        *({"table": "framework", **r} for r in framework_runs),
        *({"table": "multi-step", **r} for r in (multi.runs if multi is not None else [])),
    ]
    return report


def _row(
    report: ExperimentReport,
    table: str,
    row: str,
    column: str,
    scene: str,
    values: Sequence[float],
    n: int,
    paper: float | None = None,
) -> None:
    m, s = mean_std(values)
    report.csv_rows.append([table, row, column, scene, m, s, n, paper])


def _tab1(report: ExperimentReport, names: list[str], by_method: dict, n: int) -> str:
    scores: dict[str, dict[str, list[float]]] = {s: {} for s in TAB1_SOURCES}
    for source, (method, key) in TAB1_FROM.items():
        for scene in names:
            scores[source][scene] = [float(r[key]) for r in by_method[(scene, method)]]
    rows = []
    for scene in names:
        rows.append([scene, *(_stat_cell(scores[s][scene], n) for s in TAB1_SOURCES)])
        for s in TAB1_SOURCES:
            _row(report, "tab1", s, "label_miou", scene, scores[s][scene], n)
    means = {s: _per_seed_mean(scores[s]) for s in TAB1_SOURCES}
    rows.append(["**mean**", *(_stat_cell(means[s], n) for s in TAB1_SOURCES)])
    rows.append(
        ["paper (10 ScanNet scenes)", *(_paper(paper_numbers.TAB1[s]) for s in TAB1_SOURCES)]
    )
    for s in TAB1_SOURCES:
        _row(report, "tab1", s, "label_miou", "mean", means[s], n, paper_numbers.TAB1[s])
    groups = [TAB1_TITLES[s] for s in TAB1_SOURCES]
    report.plots.append(
        _bars(
            "paper-tab1.png",
            "Tab. 1: pseudo-label mIoU on the training views",
            groups,
            names,
            [[scores[s][scene] for s in TAB1_SOURCES] for scene in names],
            [means[s] for s in TAB1_SOURCES],
            [paper_numbers.TAB1[s] for s in TAB1_SOURCES],
        )
    )
    gap = {s: float(np.mean(means[s])) for s in TAB1_SOURCES}
    order = " < ".join(TAB1_TITLES[s] for s in sorted(TAB1_SOURCES, key=lambda k: gap[k]))
    return (
        "## Tab. 1: pseudo-label quality (mIoU % on the training views)\n\n"
        "Network: the pre-trained network's predictions (AdaBN before labelling where the "
        "preset says so); Mapping: the predictions fused in a voxel map; NeRF: rendered "
        "after the whole fit (the GI+NL runs); Ours, joint training: the NeRF's labels after "
        "the last joint round (the joint runs).\n\n"
        + markdown_table(["scene", *(f"{g} %" for g in groups)], rows)
        + f"\n\nOrdering of the means here: {order} (paper: Network < Mapping < NeRF < joint)."
    )


def _bars(
    file: str,
    title: str,
    groups: list[str],
    scenes: list[str],
    per_scene: list[list[list[float]]],
    means: list[list[float]],
    paper: list[float | None],
) -> Bars:
    """Bars per group (label source or method): one per scene, the mean over scenes, and the
    paper's number hatched; ``per_scene[i][g]`` are scene i's per-seed values of group g."""
    series = []
    for i, scene in enumerate(scenes):
        stats = [mean_std(v) for v in per_scene[i]]
        series.append(Series(scene, [], [100 * m for m, _ in stats], [100 * s for _, s in stats]))
    stats = [mean_std(v) for v in means]
    series.append(
        Series("mean", [], [100 * m for m, _ in stats], [100 * s for _, s in stats], color="k")
    )
    series.append(
        Series(
            "paper (10 ScanNet scenes)",
            [],
            [float("nan") if p is None else p for p in paper],
            color="0.6",
        )
    )
    return Bars(file, title, "mIoU %", groups, series, hatched=["paper (10 ScanNet scenes)"])


def _tab2(
    report: ExperimentReport, names: list[str], before: dict[str, float], by_method: dict, n: int
) -> str:
    methods = [m for m in TAB2_METHODS if all((s, m) in by_method for s in names)]
    header = ["method", *names, "mean", "gain (points)", "paper"]
    rows = [
        [
            "pre-trained",
            *(pct(before[s]) for s in names),
            pct(np.mean(list(before.values()))),
            "",
            _paper(paper_numbers.TAB2["pretrained"]),
        ]
    ]
    mean_before = float(np.mean([before[s] for s in names]))
    groups, per_scene, means, paper = (
        ["pre-trained"],
        [[[before[s]]] for s in names],
        [[mean_before]],
        [paper_numbers.TAB2["pretrained"]],
    )
    for method in methods:
        values = {s: [float(r["after"]["val"]) for r in by_method[(s, method)]] for s in names}
        per_seed = _per_seed_mean(values)
        rows.append(
            [
                one_step.TITLES[method],
                *(_stat_cell(values[s], n) for s in names),
                _stat_cell(per_seed, n),
                _stat_cell([v - mean_before for v in per_seed], n, signed=True),
                _paper(paper_numbers.TAB2.get(method)),
            ]
        )
        for s in names:
            _row(report, "tab2", method, "val_miou", s, values[s], n)
        _row(
            report, "tab2", method, "val_miou", "mean", per_seed, n, paper_numbers.TAB2.get(method)
        )
        groups.append(one_step.TITLES[method])
        for i, s in enumerate(names):
            per_scene[i].append(values[s])
        means.append(per_seed)
        paper.append(paper_numbers.TAB2.get(method))
    report.plots.append(
        _bars(
            "paper-tab2.png",
            "Tab. 2: validation mIoU after one-step adaptation",
            groups,
            names,
            per_scene,
            means,
            paper,
        )
    )
    return (
        "## Tab. 2: one-step adaptation (validation mIoU %)\n\n"
        "Each scene on its own, from the same pre-trained network. The paper reports no "
        'Mapping or CoTTA number in docs/method.md "Reference numbers".\n\n'
        + markdown_table(header, rows)
    )


def _tab3(
    report: ExperimentReport,
    inputs: ExperimentInputs,
    multi: ExperimentReport,
    n: int,
    adabn: Sequence[Sequence[float]] = (),
) -> str:
    names = [s.name for s in inputs.scenes]
    runs = _by(multi.runs, "method", "adabn")
    rows, acc, bwt, groups = [], [], [], []
    adabn_text = ""
    if adabn:
        # AdaBN alone: told which scene it is in, so it forgets nothing (BWT 0 by
        # construction) and its mean over the scenes is its ACC; no FWT (it never trains).
        per_scene = np.asarray(adabn, dtype=np.float64)  # (seeds, scenes)
        acc_adabn = per_scene.mean(axis=1).tolist()
        rows.append(["AdaBN alone (reference)", _stat_cell(acc_adabn, n), "", "", ""])
        _row(report, "tab3", "adabn-alone", "acc", "", acc_adabn, n)
        for j, name in enumerate(names):
            _row(report, "tab3", "adabn-alone", "val", name, per_scene[:, j].tolist(), n)
        groups.append("AdaBN alone")
        acc.append(acc_adabn)
        bwt.append([0.0] * len(acc_adabn))
        cells = " / ".join(_stat_cell(per_scene[:, j].tolist(), n) for j in range(len(names)))
        adabn_text = (
            "\n\nAdaBN alone (the pre-trained network with BatchNorm statistics re-estimated on "
            f"each scene's training camera images, no training), per scene: {cells}. It is a "
            "reference, not a continual method: it is told which scene it is in, so it forgets "
            "nothing and its ACC is the mean of these."
        )
    for (method, _adabn), done in runs.items():
        title = multi_step.TITLES[method]
        metric = {k: [float(r["metrics"][k]) for r in done] for k in multi_step.METRICS}
        rows.append(
            [title, *(_stat_cell(metric[k], n, k in ("fwt", "bwt")) for k in multi_step.METRICS)]
        )
        for k in multi_step.METRICS:
            _row(report, "tab3", method, k, "", metric[k], n)
        groups.append(title)
        acc.append(metric["acc"])
        bwt.append(metric["bwt"])
        R = np.nanmean(np.stack([np.array(r["R"], dtype=np.float64) for r in done]), axis=0)
        report.plots.append(
            Heatmap(
                file=f"paper-tab3-R-{method}.png",
                title=f"R, {title} (val mIoU %)",
                values=(100 * R).tolist(),
                row_labels=[f"after {i + 1}: {s}" for i, s in enumerate(names)],
                col_labels=names,
                xlabel="scored on scene j",
                ylabel="after step i",
                vmin=0.0,
                vmax=100.0,
            )
        )
    report.plots.append(
        Bars(
            "paper-tab3-acc-bwt.png",
            "Tab. 3: ACC and BWT per method",
            "mIoU points",
            groups,
            [
                Series(
                    "ACC",
                    [],
                    [100 * mean_std(v)[0] for v in acc],
                    [100 * mean_std(v)[1] for v in acc],
                ),
                Series(
                    "BWT",
                    [],
                    [100 * mean_std(v)[0] for v in bwt],
                    [100 * mean_std(v)[1] for v in bwt],
                ),
            ],
        )
    )
    for plot in multi.plots:
        report.plots.append(dataclasses.replace(plot, file="paper-tab3.png"))
    report.extra_csv["paper-tab3"] = (multi.csv_header, multi.csv_rows)
    report.extra_csv.update(
        {k.replace("multi-step", "paper-tab3"): v for k, v in multi.extra_csv.items()}
    )
    return (
        "## Tab. 3: multi-step adaptation\n\n"
        + multi.markdown.split("\n", 2)[-1].strip()
        + "\n\nACC, A, FWT and BWT (mIoU points):\n\n"
        + markdown_table(["method", *(k.upper() for k in multi_step.METRICS)], rows)
        + adabn_text
        + '\n\nThe paper\'s Tab. 3 numbers are not in docs/method.md "Reference numbers": '
        "none shown."
    )


def _ablations(
    report: ExperimentReport, names: list[str], by_method: dict, ablation_runs: list[dict], n: int
) -> str:
    variants = {"paper": {s: by_method[(s, ABLATION_METHOD)] for s in names}}
    for (variant,), done in _by(ablation_runs, "variant").items():
        variants[variant] = {s: [r for r in done if r["scene"] == s] for s in names}
    rows = []
    labels, afters = {}, {}
    for variant, per_scene in variants.items():
        label = {s: [float(r["pseudo_label_miou"]) for r in per_scene[s]] for s in names}
        after = {s: [float(r["after"]["val"]) for r in per_scene[s]] for s in names}
        labels[variant], afters[variant] = _per_seed_mean(label), _per_seed_mean(after)
        rows.append(
            [
                ABLATION_TITLES[variant],
                _stat_cell(labels[variant], n),
                _stat_cell(afters[variant], n),
                *(_stat_cell(label[s], n) for s in names),
            ]
        )
        for s in names:
            _row(report, "ablations", variant, "nerf_label_miou", s, label[s], n)
            _row(report, "ablations", variant, "gi_nl_val_miou", s, after[s], n)
        _row(report, "ablations", variant, "nerf_label_miou", "mean", labels[variant], n)
        _row(report, "ablations", variant, "gi_nl_val_miou", "mean", afters[variant], n)
    groups = [ABLATION_TITLES[v].split(":")[0] for v in variants]
    report.plots.append(
        Bars(
            "paper-ablations.png",
            "Ablations: NeRF labels and GI+NL after adaptation",
            "mIoU %",
            groups,
            [
                Series(
                    "NeRF labels (train views)",
                    [],
                    [100 * mean_std(labels[v])[0] for v in variants],
                    [100 * mean_std(labels[v])[1] for v in variants],
                ),
                Series(
                    "GI+NL val mIoU",
                    [],
                    [100 * mean_std(afters[v])[0] for v in variants],
                    [100 * mean_std(afters[v])[1] for v in variants],
                ),
            ],
        )
    )
    header = ["variant", "NeRF labels %", "GI+NL after %", *(f"labels {s} %" for s in names)]
    return (
        "## Ablations: semantic loss and depth loss (supplementary)\n\n"
        "GI+NL one-step runs: the NeRF's labels on the training views after the whole fit, "
        "and validation mIoU after fine-tuning on them. The first row is Tab. 2's GI+NL runs; "
        "the others change one NeRF loss (`loss.semantic_form`, `loss.depth`; "
        'docs/presets.md "NeRF presets"). The paper\'s ablation numbers are not in '
        'docs/method.md "Reference numbers".\n\n' + markdown_table(header, rows)
    )


def _framework(report: ExperimentReport, inputs: ExperimentInputs, runs: list[dict], n: int) -> str:
    from csa_core.experiments.report import byte_unit

    rows = []
    unit, scale = byte_unit([r["checkpoint_bytes"] for r in runs])
    for (preset_name,), done in _by(runs, "preset").items():
        per_seed = {
            k: [float(np.mean([r[k] for r in done if r["seed"] == seed])) for seed in inputs.seeds]
            for k in FRAMEWORK_METRICS
        }
        for k in FRAMEWORK_METRICS:
            _row(report, "framework", preset_name, k, "mean", per_seed[k], n)
        psnr, miou = mean_std(per_seed["val_psnr"]), mean_std(per_seed["label_miou"])
        rows.append(
            [
                preset_name,
                f"{psnr[0]:.2f}" + (f" ± {psnr[1]:.2f}" if n > 1 else ""),
                pct(*miou, n),
                f"{np.mean(per_seed['checkpoint_bytes']) / scale:.2f}",
                f"{np.mean(per_seed['step_seconds']):.3f}",
                f"{np.mean(per_seed['render_seconds_per_view']):.3f}",
            ]
        )
    p = paper_numbers.FRAMEWORK
    rows.append(
        ["paper (RTX 3090)", "-", "-", f"{p['checkpoint_mb']:.0f} MB", f"{p['step_seconds']}", "-"]
    )
    rows.append(
        [
            "paper: Semantic-NeRF MLP",
            "-",
            "-",
            f"{p['mlp_checkpoint_mb']} MB",
            f"{p['mlp_slowdown']:.0f}x slower to train",
            "-",
        ]
    )
    header = [
        "NeRF preset",
        "val PSNR dB",
        "label mIoU %",
        f"checkpoint {unit}",
        "s / step",
        "render s / view",
    ]
    return (
        "## NeRF frameworks (supplementary)\n\n"
        'Per NeRF preset (docs/presets.md "NeRF presets"), a fit to each scene\'s predictions '
        "with the run's budget (the fine-tuning modes' fit): PSNR of the validation views, "
        "mIoU of the labels rendered at the training views, checkpoint size (the preset's "
        "storage dtype), seconds per fit step and per rendered training view (colour and "
        "labels), means over scenes, on this machine.\n\n" + markdown_table(header, rows)
    )
