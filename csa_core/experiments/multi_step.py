"""Experiment ``multi-step``: the continual protocol for every method (paper Tab. 3).

Each (method, AdaBN setting, seed) is one :func:`run_continual` over the whole sequence from
the pre-trained network, in its own folder under
``runs/multi-step/<method>/adabn-<on|off>/seed<k>`` (with its ``results.json``). ``--adabn
both`` runs every method with and without AdaBN (``AdaptConfig.adabn``, which every method
honours, CoTTA included), so a method's gain can be told apart from AdaBN's. Per step i the
table shows "Adapt", R[i, i] (the scene just adapted to), and "Previous", the mean of R[i, j]
over the scenes j < i seen before (forgetting shows here), then ACC, A, FWT and BWT; the plot
draws both rows per method over the steps. ``--resume`` reuses the runs an earlier
invocation into the same ``--out`` finished with the same inputs
(``ExperimentInputs.finished_run``) and does the rest: a long experiment can be stopped and
continued, or split over processes that write different methods into copies of one folder.

Besides ours, Mapping, CoTTA and fine-tuning (the default list), ``--methods`` can name the
paper's two other rows of ours: ``ours-pretrain-replay``, "Ours (I_pre replay only)", and
``ours-novel-views``, "Ours (novel viewpoints)" (``csa_core.adapt.methods.OURS_VARIANTS``);
each run records the config it ran with, the variant's replay fields included.
"""

from __future__ import annotations

import logging

import numpy as np

from csa_core.adapt.continual import run_continual, val_mious
from csa_core.adapt.methods import METHODS, OURS_VARIANTS, method_config
from csa_core.eval.continual import previous_row
from csa_core.experiments.inputs import ExperimentInputs
from csa_core.experiments.report import (
    ExperimentReport,
    Plot,
    Series,
    markdown_table,
    mean_std,
    pct,
)

log = logging.getLogger(__name__)

NAME = "multi-step"
DEFAULT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m not in OURS_VARIANTS)
ALLOWED_METHODS: tuple[str, ...] = METHODS
TITLES = {
    "ours": "CSA (ours)",
    "mapping": "Mapping",
    "cotta": "CoTTA",
    "finetune": "fine-tune (no replay)",
    # The paper's Tab. 3 rows of the same names.
    "ours-pretrain-replay": "CSA (ours), I_pre replay only",
    "ours-novel-views": "CSA (ours), novel viewpoints",
}
METRICS: tuple[str, ...] = ("acc", "a", "fwt", "bwt")


def adapt_row(R: np.ndarray) -> np.ndarray:
    """R[i, i] for every step i."""
    return np.diagonal(R).copy()


def adabn_name(adabn: bool) -> str:
    return "on" if adabn else "off"


def run(inputs: ExperimentInputs) -> ExperimentReport:
    """One continual run per method, AdaBN setting and seed; see the module docstring."""
    methods = list(inputs.methods or DEFAULT_METHODS)
    variants = inputs.adabn_variants()
    entries = [(m, a) for m in methods for a in variants]
    results: dict[tuple[str, bool], list] = {e: [] for e in entries}
    runs = []
    # With --resume, the pre-trained network's scores identify it in earlier runs' records.
    b = val_mious(inputs.network(), inputs.scenes, inputs.device) if inputs.resume else None
    for method, adabn in entries:
        for seed in inputs.seeds:
            config = method_config(method, inputs.config(seed, adabn=adabn))
            parts = (NAME, method, f"adabn-{adabn_name(adabn)}", f"seed{seed}")
            work = inputs.out.joinpath("runs", *parts)
            result = inputs.finished_run(parts, config, method, b) if b is not None else None
            if result is not None:
                log.info(
                    "%s, AdaBN %s, seed %d: finished earlier, reused (--resume)",
                    method,
                    adabn_name(adabn),
                    seed,
                )
            else:
                work = inputs.run_folder(*parts)
                result = run_continual(
                    inputs.network(),
                    inputs.scenes,
                    config,
                    work,
                    inputs.pretrain_scenes,
                    save_model=False,
                    method=method,
                )
            results[(method, adabn)].append(result)
            runs.append(
                {
                    "method": method,
                    "adabn": adabn,
                    "seed": seed,
                    "results": str(work / "results.json"),
                    "R": result.R.tolist(),
                    "b": result.b.tolist(),
                    "metrics": result.metrics,
                    "memory_bytes": result.memory_bytes,
                    "seconds": result.seconds,
                    "config": result.config,
                }
            )
    return _report(inputs, entries, results, runs, len(variants) > 1)


def title(method: str, adabn: bool, both: bool) -> str:
    """A method's row title; with both AdaBN settings in the table, which one the row is."""
    if not both:
        return TITLES[method]
    return f"{TITLES[method]}, {'with' if adabn else 'without'} AdaBN"


def _report(
    inputs: ExperimentInputs,
    entries: list[tuple[str, bool]],
    results: dict[tuple[str, bool], list],
    runs: list[dict],
    both: bool,
) -> ExperimentReport:
    n = len(inputs.seeds)
    names = [s.name for s in inputs.scenes]
    T = len(names)
    first = results[entries[0]][0]
    header = [
        "method",
        "",
        *(f"{i + 1}: {name}" for i, name in enumerate(names)),
        *(m.upper() for m in METRICS),
    ]
    rows = [["pre-trained", "", *(pct(v) for v in first.b), *([""] * len(METRICS))]]
    csv_rows, metric_rows, plots_series = [], [], []
    for k, (method, adabn) in enumerate(entries):
        done = results[(method, adabn)]
        adapt = np.stack([adapt_row(r.R) for r in done])  # seeds x T
        prev = np.stack([previous_row(r.R) for r in done])
        a_stats = [mean_std(adapt[:, i]) for i in range(T)]
        p_stats = [mean_std(prev[:, i]) for i in range(T)]
        m_stats = {key: mean_std(r.metrics[key] for r in done) for key in METRICS}
        name = title(method, adabn, both)
        rows.append(
            [
                name,
                "Adapt",
                *(pct(m, s, n) for m, s in a_stats),
                *(pct(*m_stats[key], n, signed=key in ("fwt", "bwt")) for key in METRICS),
            ]
        )
        rows.append([name, "Previous", *(pct(m, s, n) for m, s in p_stats), *([""] * len(METRICS))])
        on = adabn_name(adabn)
        for i in range(T):
            csv_rows.append(
                [method, on, i, names[i], *a_stats[i], *p_stats[i], float(first.b[i]), n]
            )
        metric_rows.append([method, on, *(v for key in METRICS for v in m_stats[key]), n])
        x = list(range(1, T + 1))
        plots_series.append(
            Series(
                f"{name}: adapt",
                x,
                [m for m, _ in a_stats],
                [s for _, s in a_stats],
                style="-" if adabn or not both else "-.",
                color=f"C{k}",
            )
        )
        plots_series.append(
            Series(
                f"{name}: previous",
                x[1:],
                [m for m, _ in p_stats][1:],
                [s for _, s in p_stats][1:],
                style="--",
                marker="s",
                color=f"C{k}",
            )
        )
    plots_series.append(
        Series(
            "pre-trained", list(range(1, T + 1)), list(first.b), style=":", marker="x", color="0.5"
        )
    )
    for s in plots_series:
        s.y = [100 * v for v in s.y]
        s.std = [100 * v for v in s.std] if s.std is not None else None
    md = (
        f"### Multi-step (continual) adaptation: validation mIoU % per step "
        f"({n} seed{'s' * (n > 1)}, preset {inputs.preset})\n\n"
        "Adapt: R[i, i], the scene just adapted to; Previous: mean of R[i, j < i]. "
        "ACC, A, FWT, BWT in mIoU points. "
        + (
            "Every method runs with and without AdaBN (BatchNorm statistics re-estimated on "
            "each scene's camera images).\n\n"
            if both
            else f"AdaBN {adabn_name(entries[0][1])} for every method.\n\n"
        )
        + markdown_table(header, rows)
    )
    plot = Plot(
        file=f"{NAME}.png",
        title="Validation mIoU per step",
        xlabel="step (scene)",
        ylabel="mIoU %",
        series=plots_series,
        xticks=list(range(1, T + 1)),
        xticklabels=names,
    )
    return ExperimentReport(
        name=NAME,
        markdown=md,
        csv_header=[
            "method",
            "adabn",
            "step",
            "scene",
            "adapt_mean",
            "adapt_std",
            "previous_mean",
            "previous_std",
            "pretrained",
            "seeds",
        ],
        csv_rows=csv_rows,
        runs=runs,
        plots=[plot],
        extra_csv={
            f"{NAME}-metrics": (
                [
                    "method",
                    "adabn",
                    *(f"{k}_{s}" for k in METRICS for s in ("mean", "std")),
                    "seeds",
                ],
                metric_rows,
            )
        },
    )
