"""The paper's experiments on any scene sequence: pseudo-label quality, one-step adaptation,
multi-step (continual) adaptation and memory footprint, for our method and the baselines.

Each experiment is one module with ``NAME`` and ``run(inputs) -> ExperimentReport``;
:mod:`csa_core.experiments.report` writes the tables, plots and ``config.json``.
:mod:`csa_core.experiments.paper` (``csa experiment paper``) runs them together into one
report of the paper's tables, with the paper's numbers beside ours.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from csa_core.experiments.inputs import ExperimentInputs
    from csa_core.experiments.report import ExperimentReport

# experiment name -> module (in the order of the paper's sections)
EXPERIMENTS: dict[str, str] = {
    "pseudo-labels": "csa_core.experiments.pseudo_labels",
    "one-step": "csa_core.experiments.one_step",
    "multi-step": "csa_core.experiments.multi_step",
    "footprint": "csa_core.experiments.footprint",
}

# What ``csa experiment paper --tables`` may name, in the report's order, and the NeRF presets
# of its frameworks table by default (here, not in csa_core.experiments.paper, so that building
# the command line imports no torch).
PAPER_TABLES: tuple[str, ...] = ("1", "2", "3", "ablations", "framework")
PAPER_FRAMEWORKS: tuple[str, ...] = ("reference", "fast")


def experiment_module(name: str) -> ModuleType:
    """The module of experiment ``name``."""
    return importlib.import_module(EXPERIMENTS[name])


def allowed_methods(name: str) -> tuple[str, ...]:
    """Methods ``--methods`` may name for experiment ``name`` (empty: the option does not apply)."""
    return tuple(getattr(experiment_module(name), "ALLOWED_METHODS", ()))


def run_experiment(name: str, inputs: ExperimentInputs) -> tuple[ExperimentReport, list[Path]]:
    """Run experiment ``name`` on ``inputs`` and write its outputs to ``inputs.out``; returns
    the report and the paths written."""
    from csa_core.experiments.inputs import versions
    from csa_core.experiments.report import write_report

    report = experiment_module(name).run(inputs)
    written = write_report(report, inputs.out, inputs.describe(), versions())
    return report, written
