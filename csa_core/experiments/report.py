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
    """Mean and sample std of the finite ``values`` (NaN, NaN when there are none; std 0 for one)."""
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
class ExperimentReport:
    """What an experiment produced; :func:`write_report` puts it on disk."""

    name: str
    markdown: str
    csv_header: list[str]
    csv_rows: list[list[Any]]
    runs: list[dict[str, Any]] = field(default_factory=list)
    plots: list[Plot] = field(default_factory=list)
    extra_csv: dict[str, tuple[list[str], list[list[Any]]]] = field(default_factory=dict)


def save_plot(path: Path, plot: Plot) -> None:
    """Render ``plot`` to a PNG at ``path`` with matplotlib's Agg canvas (no pyplot, no
    global backend switch, so it is safe in a server process or a test run)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
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
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png")


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
    """A value JSON can hold: NaN and infinity become null (JSON has neither); tuples lists; paths strings."""
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
