"""Continual adaptation over a sequence of scenes (DESIGN.md "Remember" and "Protocols").

Step i: render the replay buffer from the memory bank (scenes 0..i-1), adapt to scene i
with it and with the pre-training slice, add scene i's NeRF to the bank, then score every
scene's validation views (future ones too: FWT needs R[i-1, i]) to fill row i of R.
b[j] is the pre-trained network on scene j. Results go to ``out/results.json`` after
every step, with the full config, so an interrupted run still leaves its finished steps.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from csa_core.adapt.collapse import label_entropy
from csa_core.adapt.config import AdaptConfig
from csa_core.adapt.finetune import adapt_one_step
from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.replay import PretrainReplay, ReplayBuffer
from csa_core.atomic_io import write_text_atomic
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.eval.continual import continual_metrics
from csa_core.seg.checkpoint import ModelCard, save_checkpoint
from csa_core.seg.models import SegmentationNet
from csa_core.seg.predict import evaluate_scene

log = logging.getLogger(__name__)


@dataclass
class ContinualResult:
    """R (T x T, mIoU fractions), b (T), the continual metrics and per-step records."""

    scenes: list[str]
    R: np.ndarray
    b: np.ndarray
    metrics: dict[str, float]
    steps: list[dict[str, Any]] = field(default_factory=list)
    config: dict[str, Any] = field(default_factory=dict)
    memory_bytes: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenes": self.scenes,
            "R": _nan_to_none(self.R.tolist()),
            "b": _nan_to_none(self.b.tolist()),
            "metrics": _nan_to_none(self.metrics),
            "steps": self.steps,
            "config": self.config,
            "memory_bytes": self.memory_bytes,
            "seconds": self.seconds,
        }


def _nan_to_none(value: Any) -> Any:
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    return value


def val_mious(
    model: SegmentationNet, scenes: Sequence[Scene], device: str | None = None
) -> np.ndarray:
    """mIoU of the model on every scene's validation views."""
    return np.array([evaluate_scene(model, s, "val", device=device).miou() for s in scenes])


def run_continual(
    model: SegmentationNet,
    scenes: Sequence[Scene],
    config: AdaptConfig,
    out: str | Path,
    pretrain_scenes: Sequence[Scene] = (),
    save_model: bool = True,
) -> ContinualResult:
    """Adapt ``model`` in place to ``scenes`` in order, with NeRF replay from a memory bank in
    ``out/memory`` and a ``config.replay.pretrain_fraction`` slice of ``pretrain_scenes``.

    Writes ``out/results.json`` (updated after each step) and, with ``save_model``,
    ``out/model.safetensors`` (the final network). Labels of ``scenes`` are read only to score.
    """
    if not scenes:
        raise CSAInputError("continual", "no scenes to adapt to")
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise CSAInputError("continual", f"scene names must be unique, got {names}")
    for s in scenes:
        if not any(NYU40_FOLDER in f.labels for f in s.val_frames):
            raise CSAInputError(
                s.root or s.name, "validation views need ground-truth labels to fill R"
            )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    device = config.seg.device
    bank = MemoryBank(out / "memory")
    pretrain = (
        PretrainReplay.from_scenes(
            pretrain_scenes, config.replay.pretrain_fraction, config.replay.seed
        )
        if pretrain_scenes
        else None
    )
    prior = (
        label_entropy(
            lab
            for s in pretrain_scenes
            for f in s.train_frames
            for k, lab in f.labels.items()
            if k == NYU40_FOLDER
        )
        if pretrain_scenes
        else None
    )
    T = len(scenes)
    b = val_mious(model, scenes, device)
    R = np.full((T, T), np.nan)
    result = ContinualResult(
        scenes=names,
        R=R,
        b=b,
        metrics={},
        config={**config.to_dict(), "pretrain_scenes": [s.name for s in pretrain_scenes]},
    )
    if pretrain is not None:
        result.memory_bytes["pretrain_replay"] = pretrain.nbytes()
    for i, scene in enumerate(scenes):
        t0 = time.perf_counter()
        previous = [n for n in bank.scenes if n != scene.name]
        replay = (
            ReplayBuffer.from_memory_bank(
                bank,
                config.replay.buffer_size,
                config.replay.views,
                previous,
                config.replay.max_render_samples,
            )
            if previous
            else None
        )
        t_replay = time.perf_counter() - t0
        step = adapt_one_step(
            model, scene, config, replay, pretrain, prior_entropy=prior, evaluate_before=False
        )
        entry = bank.add(scene.name, step.nerf) if step.nerf is not None else None
        t_eval = time.perf_counter()
        R[i] = val_mious(model, scenes, device)
        record = step.to_dict()
        record["seconds"] = {
            **record["seconds"],
            "replay_render": t_replay,
            "evaluate_all": time.perf_counter() - t_eval,
            "step": time.perf_counter() - t0,
        }
        record["step"] = i
        record["replay"] = replay.per_scene() if replay is not None else {}
        record["replay_bytes"] = replay.nbytes() if replay is not None else 0
        record["nerf_bytes"] = entry.bytes if entry is not None else 0
        record["R_row"] = R[i].tolist()
        result.steps.append(record)
        log.info(
            "step %d/%d %s: val mIoU %.1f%% (pre-trained %.1f%%), %.0fs",
            i + 1,
            T,
            scene.name,
            100 * R[i, i],
            100 * b[i],
            record["seconds"]["step"],
        )
        result.memory_bytes = {
            **result.memory_bytes,
            "nerf_per_scene": bank.bytes_per_scene(),
            "nerf_total": bank.total_bytes(),
        }
        result.seconds = time.perf_counter() - start
        _write(out, result)
    result.metrics = continual_metrics(R, b)
    result.seconds = time.perf_counter() - start
    _write(out, result)
    if save_model:
        card = ModelCard.for_model(
            model,
            train_config={"task": "continual", "scenes": names, "adapt": config.to_dict()},
            metrics=_nan_to_none(result.metrics),
        )
        save_checkpoint(out / "model.safetensors", model, card)
    return result


def _write(out: Path, result: ContinualResult) -> None:
    write_text_atomic(
        out / "results.json", json.dumps(result.to_dict(), indent=2, default=float) + "\n"
    )


def format_table(result: ContinualResult) -> str:
    """Markdown: pre-trained vs after-each-step mIoU per scene (percent), then ACC/A/FWT/BWT."""
    head = "| after step | " + " | ".join(result.scenes) + " |"
    rows = [head, "|" + "---|" * (len(result.scenes) + 1)]
    rows.append("| pre-trained | " + " | ".join(f"{100 * v:.1f}" for v in result.b) + " |")
    for i, row in enumerate(result.R):
        rows.append(
            f"| {i} ({result.scenes[i]}) | " + " | ".join(f"{100 * v:.1f}" for v in row) + " |"
        )
    m = result.metrics
    if m:
        rows.append("")
        rows.append(
            "ACC {:.1f}  A {:.1f}  FWT {:+.1f}  BWT {:+.1f}  (mIoU points)".format(
                *(100 * m[k] for k in ("acc", "a", "fwt", "bwt"))
            )
        )
    return "\n".join(rows)
