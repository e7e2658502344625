"""Continual adaptation over a sequence of scenes (docs/method.md "Remember" and "Protocols and
metrics").

Step i: adapt to scene i with the run's method (:func:`csa_core.adapt.step.continual_step`,
the step the service's adapt job runs too), then score every scene's validation views
(future ones too: FWT needs R[i-1, i]) to fill row i of R. For our method (the default) a
step renders the replay buffer from the memory bank (scenes 0..i-1, kept in ``out/memory``),
adapts with it and with the pre-training slice, and adds scene i's NeRF to the bank; the
baselines are in :mod:`csa_core.adapt.methods`. b[j] is the pre-trained network on scene j.
Results go to ``out/results.json`` after every step, with the full config, so an
interrupted run still leaves its finished steps.
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

from csa_core.adapt.config import AdaptConfig
from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.methods import ContinualState, check_method
from csa_core.adapt.step import continual_step
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

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ContinualResult:
        """The inverse of :meth:`to_dict` (``None`` in R, b and the metrics back to NaN)."""

        def nan(v: Any) -> float:
            return float("nan") if v is None else float(v)

        return cls(
            scenes=list(d["scenes"]),
            R=np.array([[nan(v) for v in row] for row in d["R"]], dtype=np.float64),
            b=np.array([nan(v) for v in d["b"]], dtype=np.float64),
            metrics={k: nan(v) for k, v in d["metrics"].items()},
            steps=list(d.get("steps", [])),
            config=dict(d.get("config", {})),
            memory_bytes=dict(d.get("memory_bytes", {})),
            seconds=float(d.get("seconds", 0.0)),
        )

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
    method: str = "ours",
    parent: ModelCard | None = None,
) -> ContinualResult:
    """Adapt ``model`` in place to ``scenes`` in order, with NeRF replay from a memory bank in
    ``out/memory`` and a ``config.replay.pretrain_fraction`` slice of ``pretrain_scenes``.

    ``method`` picks the method (:data:`csa_core.adapt.methods.METHODS`): ``ours`` (the
    above, in ``config.mode``), ``mapping``, ``cotta`` or ``finetune``; R, b and the metrics
    are computed alike for all. Writes ``out/results.json`` (updated after each step) and,
    with ``save_model``, ``out/model.safetensors``: the final reported network (CoTTA's
    teacher), with ``parent``'s card as its parent when given. Labels of ``scenes`` are read
    only to score.
    """
    check_method(method)
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
    state = ContinualState.start(
        config, method, bank=MemoryBank(out / "memory"), pretrain_scenes=pretrain_scenes
    )
    runner = state.method
    T = len(scenes)
    b = val_mious(model, scenes, device)
    R = np.full((T, T), np.nan)
    result = ContinualResult(
        scenes=names,
        R=R,
        b=b,
        metrics={},
        config={
            **state.config.to_dict(),  # the method's (a variant of ours sets its replay)
            "method": method,
            "method_settings": runner.settings(),
            "pretrain_scenes": [s.name for s in pretrain_scenes],
        },
    )
    if state.pretrain is not None:
        result.memory_bytes["pretrain_replay"] = state.pretrain.nbytes()
    for i, scene in enumerate(scenes):
        t0 = time.perf_counter()
        record = continual_step(state, model, scene)
        t_eval = time.perf_counter()
        R[i] = val_mious(runner.reported(model), scenes, device)
        record["seconds"] = {
            **record["seconds"],
            "evaluate_all": time.perf_counter() - t_eval,
            "step": time.perf_counter() - t0,
        }
        record["step"] = i
        record["R_row"] = R[i].tolist()
        result.steps.append(record)
        log.info(
            "%s step %d/%d %s: val mIoU %.1f%% (pre-trained %.1f%%), %.0fs",
            method,
            i + 1,
            T,
            scene.name,
            100 * R[i, i],
            100 * b[i],
            record["seconds"]["step"],
        )
        result.memory_bytes = {**result.memory_bytes, **record["memory_bytes"]}
        result.seconds = time.perf_counter() - start
        _write(out, result)
    result.metrics = continual_metrics(R, b)
    result.seconds = time.perf_counter() - start
    _write(out, result)
    if save_model:
        reported = runner.reported(model)
        values = {
            "train_config": {
                "task": "continual",
                "method": method,
                "scenes": names,
                "adapt": state.config.to_dict(),
            },
            "metrics": _nan_to_none(result.metrics),
        }
        if parent is not None:
            card = parent.child(**values)
        else:
            card = ModelCard.for_model(model, **values)
        save_checkpoint(out / "model.safetensors", reported, card)  # type: ignore[arg-type]
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
