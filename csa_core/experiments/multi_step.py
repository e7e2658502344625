"""Experiment ``multi-step``: the continual protocol for every method (paper Tab. 3).

Each (method, seed) is one :func:`run_continual` over the whole sequence from the pre-trained
network, in its own folder under ``runs/multi-step/<method>/seed<k>`` (with its
``results.json``). Per step i the table shows "Adapt", R[i, i] (the scene just adapted to),
and "Previous", the mean of R[i, j] over the scenes j < i seen before (forgetting shows
here), then ACC, A, FWT and BWT; the plot draws both rows per method over the steps.
"""

from __future__ import annotations

import numpy as np

from csa_core.adapt.continual import run_continual
from csa_core.adapt.methods import METHODS
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

NAME = "multi-step"
DEFAULT_METHODS: tuple[str, ...] = METHODS
ALLOWED_METHODS: tuple[str, ...] = METHODS
TITLES = {
    "ours": "CSA (ours)",
    "mapping": "Mapping",
    "cotta": "CoTTA",
    "finetune": "fine-tune (no replay)",
}
METRICS: tuple[str, ...] = ("acc", "a", "fwt", "bwt")


def adapt_row(R: np.ndarray) -> np.ndarray:
    """R[i, i] for every step i."""
    return np.diagonal(R).copy()


def run(inputs: ExperimentInputs) -> ExperimentReport:
    """One continual run per method and seed; see the module docstring."""
    methods = list(inputs.methods or DEFAULT_METHODS)
    results: dict[str, list] = {m: [] for m in methods}
    runs = []
    for method in methods:
        for seed in inputs.seeds:
            config = inputs.config(seed)
            work = inputs.run_folder(NAME, method, f"seed{seed}")
            result = run_continual(
                inputs.network(),
                inputs.scenes,
                config,
                work,
                inputs.pretrain_scenes,
                save_model=False,
                method=method,
            )
            results[method].append(result)
            runs.append(
                {
                    "method": method,
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
    return _report(inputs, methods, results, runs)


def _report(
    inputs: ExperimentInputs, methods: list[str], results: dict[str, list], runs: list[dict]
) -> ExperimentReport:
    n = len(inputs.seeds)
    names = [s.name for s in inputs.scenes]
    T = len(names)
    first = results[methods[0]][0]
    header = [
        "method",
        "",
        *(f"{i + 1}: {name}" for i, name in enumerate(names)),
        *(m.upper() for m in METRICS),
    ]
    rows = [["pre-trained", "", *(pct(v) for v in first.b), *([""] * len(METRICS))]]
    csv_rows, metric_rows, plots_series = [], [], []
    for k, method in enumerate(methods):
        adapt = np.stack([adapt_row(r.R) for r in results[method]])  # seeds x T
        prev = np.stack([previous_row(r.R) for r in results[method]])
        a_stats = [mean_std(adapt[:, i]) for i in range(T)]
        p_stats = [mean_std(prev[:, i]) for i in range(T)]
        m_stats = {k: mean_std(r.metrics[k] for r in results[method]) for k in METRICS}
        title = TITLES[method]
        rows.append(
            [
                title,
                "Adapt",
                *(pct(m, s, n) for m, s in a_stats),
                *(pct(*m_stats[k], n, signed=k in ("fwt", "bwt")) for k in METRICS),
            ]
        )
        rows.append(
            [title, "Previous", *(pct(m, s, n) for m, s in p_stats), *([""] * len(METRICS))]
        )
        for i in range(T):
            csv_rows.append([method, i, names[i], *a_stats[i], *p_stats[i], float(first.b[i]), n])
        metric_rows.append([method, *(v for k in METRICS for v in m_stats[k]), n])
        x = list(range(1, T + 1))
        plots_series.append(
            Series(
                f"{title}: adapt",
                x,
                [m for m, _ in a_stats],
                [s for _, s in a_stats],
                color=f"C{k}",
            )
        )
        plots_series.append(
            Series(
                f"{title}: previous",
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
        "ACC, A, FWT, BWT in mIoU points.\n\n" + markdown_table(header, rows)
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
                ["method", *(f"{k}_{s}" for k in METRICS for s in ("mean", "std")), "seeds"],
                metric_rows,
            )
        },
    )
