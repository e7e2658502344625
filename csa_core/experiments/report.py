"""Tables, plots and files shared by the experiments.

Every experiment ends in an :class:`ExperimentReport`: a Markdown table (mIoU in percent,
one decimal, ``mean ± std`` over seeds), the same numbers as CSV rows (fractions or bytes,
full precision, mean and std in separate columns), line plots, and the record of every run.
:func:`write_report` writes ``<name>.md``, ``<name>.csv``, ``config.json`` and the PNGs, each
atomically, so an interrupted experiment never leaves a half-written table behind.
``config.json`` holds one entry per experiment (seeds, inputs, versions, the config of every
run), so the four experiments can share one output folder.

Std is the sample standard deviation over seeds (``ddof=1``); with one seed it is 0 by
definition here, so the CSV never holds NaN for "no spread measured".
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from csa_core.atomic_io import atomic_file, write_text_atomic
from csa_core.errors import CSAInputError

CONFIG_FORMAT = "csa-experiments/1"


def mean_std(values: Iterable[float]) -> tuple[float, float]:
    """Mean and sample std of the finite ``values`` (NaN, NaN when there are none; std 0 for
    one)."""
    arr = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if arr.size == 0:
        return float("nan"), float("nan")
    return float(arr.mean()), float(arr.std(ddof=1)) if arr.size > 1 else 0.0


def pct(mean: float, std: float | None = None, seeds: int = 1, signed: bool = False) -> str:
    """A fraction as percent with one decimal, ``± std`` when more than one seed; ``-`` for NaN."""
    if mean is None or not math.isfinite(mean):
        return "-"
    text = f"{100 * mean:+.1f}" if signed else f"{100 * mean:.1f}"
    if seeds > 1 and std is not None and math.isfinite(std):
        text += f" ± {100 * std:.1f}"
    return text


def byte_unit(values: Iterable[float]) -> tuple[str, float]:
    """One unit for a column of byte counts: MB from a megabyte up, else kB."""
    top = max((v for v in values if math.isfinite(v)), default=0.0)
    return ("MB", 1e6) if top >= 1e6 else ("kB", 1e3)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def csv_text(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if _is_nan(v) else v for v in row])
    return buf.getvalue()


def _is_nan(value: Any) -> bool:
    return isinstance(value, float) and not math.isfinite(value)


@dataclass
class Series:
    """One line of a plot: y (and optional std as error bars) over x."""

    label: str
    x: list[float]
    y: list[float]
    std: list[float] | None = None
    style: str = "-"
    marker: str = "o"
    color: str | None = None  # matplotlib colour, e.g. "C0"; None: the next in the cycle


@dataclass
class Plot:
    """A line plot written as ``<file>`` (PNG)."""

    file: str
    title: str
    xlabel: str
    ylabel: str
    series: list[Series]
    xticks: list[float] | None = None
    xticklabels: list[str] | None = None
    logy: bool = False
    ylim: tuple[float, float] | None = None  # a fixed y range (e.g. 0-100 for a percentage)


@dataclass
class Bars:
    """Grouped bars written as ``<file>`` (PNG): one group per ``groups`` entry, one bar per
    series in each group (``std`` as error bars); a series may be hatched (e.g. the paper's
    own numbers beside ours) and may miss groups (NaN: no bar)."""

    file: str
    title: str
    ylabel: str
    groups: list[str]
    series: list[Series]  # x unused: the i-th y belongs to groups[i]
    hatched: list[str] = field(default_factory=list)  # labels of the series drawn hatched
    ylim: tuple[float, float] | None = None


@dataclass
class Heatmap:
    """A matrix written as ``<file>`` (PNG), each cell annotated; NaN cells are left blank."""

    file: str
    title: str
    values: list[list[float]]
    row_labels: list[str]
    col_labels: list[str]
    xlabel: str = ""
    ylabel: str = ""
    fmt: str = "{:.1f}"
    vmin: float | None = None
    vmax: float | None = None


@dataclass
class ExperimentReport:
    """What an experiment produced; :func:`write_report` puts it on disk."""

    name: str
    markdown: str
    csv_header: list[str]
    csv_rows: list[list[Any]]
    runs: list[dict[str, Any]] = field(default_factory=list)
    plots: list[Plot | Bars | Heatmap] = field(default_factory=list)
    extra_csv: dict[str, tuple[list[str], list[list[Any]]]] = field(default_factory=dict)


def _figure(size: tuple[float, float] = (6.4, 4.0)):
    """A matplotlib figure on an Agg canvas (no pyplot, no global backend switch, so it is
    safe in a server process or a test run) and its one axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png")


def save_plot(path: Path, plot: Plot | Bars | Heatmap) -> None:
    """Render ``plot`` (lines, grouped bars or a heatmap) to a PNG at ``path``."""
    if isinstance(plot, Bars):
        return _save_bars(path, plot)
    if isinstance(plot, Heatmap):
        return _save_heatmap(path, plot)
    fig, ax = _figure()
    for s in plot.series:
        y = np.asarray(s.y, dtype=np.float64)
        err = np.asarray(s.std, dtype=np.float64) if s.std is not None else None
        style = {"linestyle": s.style, "marker": s.marker, "label": s.label, "color": s.color}
        if err is not None and np.isfinite(err).any() and (np.nan_to_num(err) > 0).any():
            ax.errorbar(s.x, y, yerr=err, capsize=3, **style)
        else:
            ax.plot(s.x, y, **style)
    ax.set_title(plot.title)
    ax.set_xlabel(plot.xlabel)
    ax.set_ylabel(plot.ylabel)
    if plot.xticks is not None:
        ax.set_xticks(plot.xticks)
        if plot.xticklabels is not None:
            ax.set_xticklabels(plot.xticklabels, rotation=20, ha="right")
    if plot.logy:
        ax.set_yscale("log")
    if plot.ylim is not None:
        ax.set_ylim(*plot.ylim)
    ax.grid(True, alpha=0.3)
    if plot.series:
        ax.legend(fontsize="small")
    _save(fig, path)


def _save_bars(path: Path, plot: Bars) -> None:
    n_groups, n_series = len(plot.groups), max(1, len(plot.series))
    fig, ax = _figure((max(6.4, 0.5 + 0.35 * n_groups * n_series), 4.2))
    width = 0.8 / n_series
    x = np.arange(n_groups, dtype=np.float64)
    for k, s in enumerate(plot.series):
        y = np.asarray(s.y, dtype=np.float64)
        err = np.asarray(s.std, dtype=np.float64) if s.std is not None else None
        if err is not None and not (np.nan_to_num(err) > 0).any():
            err = None
        ax.bar(
            x + (k - (n_series - 1) / 2) * width,
            np.nan_to_num(y),
            width,
            yerr=None if err is None else np.nan_to_num(err),
            capsize=2,
            label=s.label,
            color=s.color,
            hatch="//" if s.label in plot.hatched else None,
            edgecolor="0.2" if s.label in plot.hatched else None,
            alpha=0.55 if s.label in plot.hatched else 1.0,
        )
    ax.axhline(0.0, color="0.3", linewidth=0.8)
    ax.set_xticks(x)
    ax.set_xticklabels(plot.groups, rotation=20, ha="right")
    ax.set_title(plot.title)
    ax.set_ylabel(plot.ylabel)
    if plot.ylim is not None:
        ax.set_ylim(*plot.ylim)
    ax.grid(True, axis="y", alpha=0.3)
    if plot.series:
        ax.legend(fontsize="small")
    _save(fig, path)


def _save_heatmap(path: Path, plot: Heatmap) -> None:
    values = np.asarray(plot.values, dtype=np.float64)
    rows, cols = values.shape
    fig, ax = _figure((max(6.4, 3.2 + 1.1 * cols), max(4.0, 1.6 + 0.6 * rows)))
    image = ax.imshow(np.ma.masked_invalid(values), cmap="viridis", vmin=plot.vmin, vmax=plot.vmax)
    fig.colorbar(image, ax=ax)
    finite = values[np.isfinite(values)]
    if plot.vmin is not None and plot.vmax is not None:
        middle = (plot.vmin + plot.vmax) / 2  # white text on the colour map's dark half
    else:
        middle = float(finite.mean()) if finite.size else 0.0
    for i in range(rows):
        for j in range(cols):
            if math.isfinite(values[i, j]):
                ax.text(
                    j,
                    i,
                    plot.fmt.format(values[i, j]),
                    ha="center",
                    va="center",
                    fontsize="small",
                    color="black" if values[i, j] > middle else "white",
                )
    ax.set_xticks(range(cols))
    ax.set_xticklabels(plot.col_labels, rotation=20, ha="right")
    ax.set_yticks(range(rows))
    ax.set_yticklabels(plot.row_labels)
    ax.set_xlabel(plot.xlabel)
    ax.set_ylabel(plot.ylabel)
    ax.set_title(plot.title)
    _save(fig, path)


def write_report(
    report: ExperimentReport, out: Path, inputs: dict[str, Any], versions: dict[str, str]
) -> list[Path]:
    """Write the table (Markdown and CSV), config.json and the plots; returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    md = out / f"{report.name}.md"
    write_text_atomic(md, report.markdown + "\n")
    written.append(md)
    table = out / f"{report.name}.csv"
    write_text_atomic(table, csv_text(report.csv_header, report.csv_rows))
    written.append(table)
    for name, (header, rows) in report.extra_csv.items():
        path = out / f"{name}.csv"
        write_text_atomic(path, csv_text(header, rows))
        written.append(path)
    for plot in report.plots:
        path = out / plot.file
        save_plot(path, plot)
        written.append(path)
    entry = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "seeds": inputs.get("seeds"),
        "inputs": inputs,
        "versions": versions,
        "runs": report.runs,
    }
    path = out / "config.json"
    doc = _read_config(path)
    doc["experiments"][report.name] = entry
    write_text_atomic(path, json.dumps(jsonable(doc), indent=2) + "\n")
    written.append(path)
    return written


def _read_config(path: Path) -> dict[str, Any]:
    """The config.json of an output folder: one entry per experiment, so several experiments
    can share a folder; a file that is not ours is an input error, never overwritten."""
    if not path.is_file():
        return {"format": CONFIG_FORMAT, "experiments": {}}
    try:
        doc = json.loads(path.read_text())
    except ValueError as e:
        raise CSAInputError(path, f"exists and is not JSON ({e}); choose another --out") from None
    if not isinstance(doc, dict) or doc.get("format") != CONFIG_FORMAT:
        raise CSAInputError(
            path, "exists and was not written by csa experiment; choose another --out"
        )
    doc.setdefault("experiments", {})
    return doc


def jsonable(value: Any) -> Any:
    """A value JSON can hold: NaN and infinity become null (JSON has neither); tuples lists; paths
    strings."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    return value
