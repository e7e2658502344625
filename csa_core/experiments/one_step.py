"""Experiment ``one-step``: adapt the pre-trained network to each scene on its own (paper Tab. 2).

Every (scene, method, seed) run starts from the same pre-trained network; methods are our
three modes (GI+NL, NI+NL, joint) and the baselines. The table gives validation mIoU before
(the pre-trained network, the same for every method) and after, and the gain. The
pre-training slice is mixed in when ``--pretrain-scenes`` are given, as in ``csa adapt``.
Each run is recorded in ``runs/one-step/<scene>/<method>/seed<k>/results.json``; ``--resume``
reuses the runs an earlier invocation finished with the same inputs (:func:`run_unit`).
"""

from __future__ import annotations

import copy
import json
import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from csa_core.adapt.config import MODES, AdaptConfig
from csa_core.adapt.continual import ContinualResult
from csa_core.adapt.finetune import evaluate
from csa_core.adapt.methods import pretrain_context
from csa_core.adapt.replay import PretrainReplay
from csa_core.adapt.step import one_step
from csa_core.atomic_io import write_text_atomic
from csa_core.data.scene import Scene
from csa_core.experiments.inputs import ExperimentInputs
from csa_core.experiments.report import (
    ExperimentReport,
    jsonable,
    markdown_table,
    mean_std,
    pct,
)

log = logging.getLogger(__name__)

NAME = "one-step"
DEFAULT_METHODS: tuple[str, ...] = ("gi_nl", "ni_nl", "joint", "mapping", "cotta")
ALLOWED_METHODS: tuple[str, ...] = (*DEFAULT_METHODS, "finetune")
TITLES = {
    "gi_nl": "GI+NL (ours)",
    "ni_nl": "NI+NL (ours)",
    "joint": "joint (ours)",
    "mapping": "Mapping",
    "cotta": "CoTTA",
    "finetune": "fine-tune on own predictions",
}

# The pre-training slice and prior entropy of a seed's config, made when a run needs them.
Context = Callable[[], tuple[PretrainReplay | None, float | None]]


def scores_before(inputs: ExperimentInputs) -> dict[str, float]:
    """The pre-trained network's validation mIoU per scene (the same for every method)."""
    base = inputs.network()
    return {scene.name: evaluate(base, scene, inputs.device)["val"] for scene in inputs.scenes}


def context(inputs: ExperimentInputs, config: AdaptConfig) -> Context:
    """:func:`pretrain_context` of ``config``, made once, on first use (a resumed experiment
    whose runs all finished never loads the pre-training slice)."""
    made: list[tuple[PretrainReplay | None, float | None]] = []

    def get() -> tuple[PretrainReplay | None, float | None]:
        if not made:
            made.append(pretrain_context(inputs.pretrain_scenes, config))
        return made[0]

    return get


def run_unit(
    inputs: ExperimentInputs,
    parts: Sequence[str],
    scene: Scene,
    method: str,
    seed: int,
    config: AdaptConfig,
    before: float,
    pretrain: Context,
) -> dict:
    """One one-step run (``method`` on ``scene`` from the pre-trained network, ``config``)
    in ``out/runs/<parts>``, and its entry for ``config.json``. The run is recorded as a
    continual run over its one scene (``results.json``: R = [[after]], b = [before], the
    step's record), so with ``--resume`` :meth:`ExperimentInputs.finished_run` finds it and
    it is read back instead of run again (the entry's ``reused``)."""
    unit = config
    if method in MODES:
        unit = copy.deepcopy(config)
        unit.mode = method
    b = np.array([before], dtype=np.float64)
    result = inputs.finished_run(parts, unit, method, b, scenes=[scene])
    reused = result is not None
    if result is None:
        t0 = time.perf_counter()
        work = inputs.run_folder(*parts)
        replay, prior = pretrain()
        record, _ = one_step(inputs.network(), scene, config, method, work, replay, prior)
        after = float(record["after"]["val"])
        result = ContinualResult(
            scenes=[scene.name],
            R=np.array([[after]]),
            b=b,
            metrics={"after": after, "gain": after - before},
            steps=[record],
            config={
                **unit.to_dict(),
                "method": method,
                "method_settings": record["method_settings"],
                "pretrain_scenes": [s.name for s in inputs.pretrain_scenes],
            },
            memory_bytes=record["memory_bytes"],
            seconds=time.perf_counter() - t0,
        )
        text = json.dumps(jsonable(result.to_dict()), indent=2) + "\n"
        write_text_atomic(work / "results.json", text)
    else:
        log.info("%s: finished earlier, reused (--resume)", "/".join(parts))
    record = result.steps[0]
    return {
        "scene": scene.name,
        "method": method,
        "seed": seed,
        "before": record["before"],
        "after": record["after"],
        "prediction_miou": record.get("prediction_miou"),
        "pseudo_label_miou": record.get("pseudo_label_miou"),
        "final_label_miou": record.get("final_label_miou"),
        "trained": record.get("trained", True),
        "seconds": result.seconds,
        "reused": reused,
        "results": str(inputs.out.joinpath("runs", *parts, "results.json")),
        "config": {**unit.to_dict(), "mode": record["mode"]},
        "method_settings": record["method_settings"],
        "memory_bytes": record["memory_bytes"],
    }


def run(inputs: ExperimentInputs) -> ExperimentReport:
    """Adapt a fresh copy of the network to each scene with each method, for every seed."""
    methods = list(inputs.methods or DEFAULT_METHODS)
    before = scores_before(inputs)
    runs = []
    for seed in inputs.seeds:
        config = inputs.config(seed)
        pretrain = context(inputs, config)
        for scene in inputs.scenes:
            for method in methods:
                parts = (NAME, scene.name, method, f"seed{seed}")
                runs.append(
                    run_unit(
                        inputs, parts, scene, method, seed, config, before[scene.name], pretrain
                    )
                )
    after: dict[tuple[str, str], list[float]] = {}
    for r in runs:
        after.setdefault((r["scene"], r["method"]), []).append(r["after"]["val"])
    return _report(inputs, methods, before, after, runs)


def _report(
    inputs: ExperimentInputs,
    methods: list[str],
    before: dict[str, float],
    after: dict[tuple[str, str], list[float]],
    runs: list[dict],
) -> ExperimentReport:
    n = len(inputs.seeds)
    names = [s.name for s in inputs.scenes]
    rows, csv_rows = [], []
    for scene in names:
        for method in methods:
            values = after[(scene, method)]
            m, s = mean_std(values)
            gain_m, gain_s = mean_std(v - before[scene] for v in values)
            rows.append(
                [
                    scene,
                    TITLES[method],
                    pct(before[scene]),
                    pct(m, s, n),
                    pct(gain_m, gain_s, n, True),
                ]
            )
            csv_rows.append([scene, method, before[scene], m, s, gain_m, gain_s, n])
    for method in methods:
        per_seed_after = [
            sum(after[(scene, method)][k] for scene in names) / len(names) for k in range(n)
        ]
        mean_before = sum(before.values()) / len(before)
        m, s = mean_std(per_seed_after)
        gain_m, gain_s = mean_std(v - mean_before for v in per_seed_after)
        rows.append(
            [
                "**mean**",
                TITLES[method],
                pct(mean_before),
                pct(m, s, n),
                pct(gain_m, gain_s, n, True),
            ]
        )
    header = ["scene", "method", "before %", "after %", "gain (points)"]
    md = (
        f"### One-step adaptation: validation mIoU ({n} seed{'s' * (n > 1)}, "
        f"preset {inputs.preset})\n\n" + markdown_table(header, rows)
    )
    return ExperimentReport(
        name=NAME,
        markdown=md,
        csv_header=[
            "scene",
            "method",
            "before",
            "after_mean",
            "after_std",
            "gain_mean",
            "gain_std",
            "seeds",
        ],
        csv_rows=csv_rows,
        runs=runs,
    )
