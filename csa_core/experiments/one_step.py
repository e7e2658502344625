"""Experiment ``one-step``: adapt the pre-trained network to each scene on its own (paper Tab. 2).

Every (scene, method, seed) run starts from the same pre-trained network; methods are our
three modes (GI+NL, NI+NL, joint) and the baselines. The table gives validation mIoU before
(the pre-trained network, the same for every method) and after, and the gain. The
pre-training slice is mixed in when ``--pretrain-scenes`` are given, as in ``csa adapt``.
"""

from __future__ import annotations

import time

from csa_core.adapt.finetune import evaluate
from csa_core.adapt.methods import pretrain_context
from csa_core.adapt.step import one_step
from csa_core.experiments.inputs import ExperimentInputs
from csa_core.experiments.report import ExperimentReport, markdown_table, mean_std, pct

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


def run(inputs: ExperimentInputs) -> ExperimentReport:
    """Adapt a fresh copy of the network to each scene with each method, for every seed."""
    methods = list(inputs.methods or DEFAULT_METHODS)
    before: dict[str, float] = {}
    after: dict[tuple[str, str], list[float]] = {}
    runs = []
    base = inputs.network()
    device = inputs.device
    for scene in inputs.scenes:
        before[scene.name] = evaluate(base, scene, device)["val"]
    for seed in inputs.seeds:
        config = inputs.config(seed)
        pretrain, prior = pretrain_context(inputs.pretrain_scenes, config)
        for scene in inputs.scenes:
            for method in methods:
                t0 = time.perf_counter()
                work = inputs.run_folder(NAME, scene.name, method, f"seed{seed}")
                record, _ = one_step(inputs.network(), scene, config, method, work, pretrain, prior)
                after.setdefault((scene.name, method), []).append(record["after"]["val"])
                runs.append(
                    {
                        "scene": scene.name,
                        "method": method,
                        "seed": seed,
                        "before": record["before"],
                        "after": record["after"],
                        "prediction_miou": record.get("prediction_miou"),
                        "pseudo_label_miou": record.get("pseudo_label_miou"),
                        "trained": record.get("trained", True),
                        "seconds": time.perf_counter() - t0,
                        "config": {**config.to_dict(), "mode": record["mode"]},
                        "method_settings": record["method_settings"],
                        "memory_bytes": record["memory_bytes"],
                    }
                )
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
