"""The learning half of ``csa demo``: pre-train the light network, adapt it continually,
summarise pre-trained vs adapted mIoU per scene and plot mIoU after every step.

Besides the method's numbers the summary has one reference row the paper does not: the
pre-trained network with AdaBN alone (BatchNorm statistics re-estimated on the scene's
camera images, no training). Our method starts every step with the same re-estimation, so
this row shows how much of the gain the pseudo-labels add on top of it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from csa_core.adapt.continual import ContinualResult
from csa_core.data.scene import Scene


def pretrain_network(
    scenes: Sequence[Scene],
    size: tuple[int, int],
    epochs: int,
    seed: int,
    device: str | None,
    out: Path,
) -> tuple[Any, dict[str, Any]]:
    """Pre-train the default light network from scratch on ``scenes``; keep the best epoch."""
    from csa_core.seg.config import PretrainConfig, TrainConfig
    from csa_core.seg.pretraining import pretrain

    config = PretrainConfig(
        size=size,
        train=TrainConfig(epochs=epochs, val_every=max(1, epochs // 4), seed=seed, device=device),
    )
    model, result = pretrain(scenes, config, out=out)
    info = {
        "checkpoint": str(out),
        "epochs": epochs,
        "train_images": sum(s.num_train for s in scenes),
        "best_epoch": result.best_epoch,
        "best_val_miou": result.best_score,
        "seconds": result.seconds,
    }
    return model, info


def summary_rows(result: ContinualResult, adabn: Sequence[float]) -> list[dict[str, Any]]:
    """Per scene: pre-trained, AdaBN only, adapted at its own step, after the last step, and
    the quality of the labels the step trained on (percent, validation views / training views)."""
    T = len(result.scenes)
    rows = []
    for j, name in enumerate(result.scenes):
        step = result.steps[j] if j < len(result.steps) else {}
        rows.append(
            {
                "scene": name,
                "pretrained": 100 * float(result.b[j]),
                "adabn_only": 100 * float(adabn[j]),
                "adapted": 100 * float(result.R[j, j]),
                "after_all": 100 * float(result.R[T - 1, j]),
                "prediction_labels": 100 * float(step.get("prediction_miou", np.nan)),
                "nerf_labels": 100 * float(step.get("pseudo_label_miou", np.nan)),
            }
        )
    return rows


def plot_steps(path: Path, result: ContinualResult) -> None:
    """mIoU of every scene's validation views, pre-trained and after every step."""
    from csa_core.experiments.report import Plot, Series, save_plot

    T = len(result.scenes)
    x = list(range(T + 1))
    series = [
        Series(
            name, x, [100 * float(result.b[j])] + [100 * float(result.R[i, j]) for i in range(T)]
        )
        for j, name in enumerate(result.scenes)
    ]
    mean = [100 * float(np.mean(result.b))] + [100 * float(np.mean(result.R[i])) for i in range(T)]
    series.append(Series("mean", x, mean, style="--", marker="s", color="k"))
    save_plot(
        path,
        Plot(
            file=path.name,
            title="validation mIoU after every adaptation step",
            xlabel="after step",
            ylabel="mIoU (%)",
            series=series,
            xticks=[float(v) for v in x],
            xticklabels=["pre-trained"] + [f"{i} ({n})" for i, n in enumerate(result.scenes)],
        ),
    )
