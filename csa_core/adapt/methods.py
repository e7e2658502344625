"""The methods one continual run can use, behind one small interface (DESIGN.md "Baselines").

:func:`csa_core.adapt.continual.run_continual` owns the protocol: the scenes and their order,
R and b, the continual metrics, ``results.json``. A method owns what happens inside one step
and what it keeps between steps, so every method is scored by the same code on the same views:

- ``ours``: NeRF pseudo-labels in ``config.mode`` (GI+NL, NI+NL or joint), replay rendered
  from the NeRF memory bank, the pre-training slice. Stores one NeRF checkpoint per scene.
- ``mapping`` (Frey et al.): the network's predictions fused in a voxel map, map labels read
  back at the training views, fine-tuning on camera images + map labels (GI+ML) with a replay
  buffer of earlier scenes' *stored* image/label pairs. Stores the map and those pairs.
- ``cotta`` (Wang et al.): one online CoTTA pass over each scene's training views with one
  CoTTA instance for the whole sequence; the teacher is the network that is scored and saved.
  Stores two extra network copies (teacher and source).
- ``finetune``: fine-tuning on the network's own predictions, no NeRF, no replay of any
  kind: the lower bound that shows what the 3D fusion and the memory add.

Mapping and the lower bound train with the same loop as ours (Adam, batch composition with
the pre-training slice where there is one, AdaBN afterwards), so a difference in R comes from
the labels and the memory, not from the optimiser. Mapping's own :func:`mapping_adapt` uses
the segmentation trainer instead, which cannot mix in the pre-training slice.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from torch import nn

from csa_core.adapt.baselines.cotta import CoTTA, CoTTAConfig
from csa_core.adapt.baselines.mapping import (
    MappingMemory,
    build_voxel_map,
    mapping_memory,
    mapping_replay_buffer,
    render_map_labels,
)
from csa_core.adapt.baselines.voxel_map import VoxelMapConfig
from csa_core.adapt.collapse import label_entropy
from csa_core.adapt.config import MODES, AdaptConfig
from csa_core.adapt.finetune import (
    adabn_slice,
    adapt_one_step,
    apply_adabn,
    evaluate,
    finetune_on_labels,
)
from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.pseudo_labels import label_miou, predict_frames
from csa_core.adapt.replay import PretrainReplay, ReplayBuffer
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.seg.models import SegmentationNet

# Methods of the continual protocol; "ours" runs config.mode.
METHODS: tuple[str, ...] = ("ours", "mapping", "cotta", "finetune")
# Methods of the one-step protocol: our three modes by name, then the baselines.
ONE_STEP_METHODS: tuple[str, ...] = (*MODES, "mapping", "cotta", "finetune")


@dataclass
class MethodContext:
    """What every method may use: the run's config, its output folder (the memory bank lives
    in ``out/memory``), the pre-training slice and the guard's prior entropy."""

    config: AdaptConfig
    out: Path
    pretrain: PretrainReplay | None = None
    prior_entropy: float | None = None


class ContinualMethod:
    """One method of the continual protocol. ``step`` adapts ``model`` in place to one scene
    and returns the step's record for ``results.json``; ``reported`` is the network that is
    scored and saved; ``memory_bytes`` is what the method stores after the steps so far,
    with ``method_total`` the bytes that count in the comparison of methods."""

    name: ClassVar[str] = ""
    # Whether a step ends with AdaBN on the scene (with ``config.adabn``), so that
    # run_continual pools the adapted scenes' statistics (csa_core.adapt.bn_memory).
    reestimates_batchnorm: ClassVar[bool] = True

    def __init__(self, context: MethodContext):
        self.context = context

    @property
    def config(self) -> AdaptConfig:
        return self.context.config

    def step(self, model: SegmentationNet, scene: Scene) -> dict[str, Any]:
        raise NotImplementedError

    def reported(self, model: SegmentationNet) -> nn.Module:
        return model

    def memory_bytes(self) -> dict[str, Any]:
        return {"method_total": 0}

    def settings(self) -> dict[str, Any]:
        """Settings of the method beyond the AdaptConfig (recorded with the results)."""
        return {}

    def _adabn(self, model: SegmentationNet, scene: Scene, pretrain: PretrainReplay | None) -> None:
        if self.config.adabn:
            apply_adabn(
                model,
                [f.color for f in scene.train_frames],
                adabn_slice(self.config, pretrain),
                self.config.seg.seed,
                self.config.seg.device,
            )


class Ours(ContinualMethod):
    """NeRF pseudo-labels in ``config.mode`` with replay from the NeRF memory bank."""

    name = "ours"

    def __init__(self, context: MethodContext):
        super().__init__(context)
        self.bank = MemoryBank(context.out / "memory")

    def step(self, model: SegmentationNet, scene: Scene) -> dict[str, Any]:
        cfg = self.config
        t0 = time.perf_counter()
        previous = [n for n in self.bank.scenes if n != scene.name]
        replay = (
            ReplayBuffer.from_memory_bank(
                self.bank,
                cfg.replay.buffer_size,
                cfg.replay.views,
                previous,
                cfg.replay.max_render_samples,
            )
            if previous
            else None
        )
        t_replay = time.perf_counter() - t0
        step = adapt_one_step(
            model,
            scene,
            cfg,
            replay,
            self.context.pretrain,
            prior_entropy=self.context.prior_entropy,
            evaluate_before=False,
        )
        entry = self.bank.add(scene.name, step.nerf) if step.nerf is not None else None
        record = step.to_dict()
        record["method"] = self.name
        record["seconds"] = {**record["seconds"], "replay_render": t_replay}
        record["replay"] = replay.per_scene() if replay is not None else {}
        record["replay_bytes"] = replay.nbytes() if replay is not None else 0
        record["nerf_bytes"] = entry.bytes if entry is not None else 0
        return record

    def memory_bytes(self) -> dict[str, Any]:
        return {
            "nerf_per_scene": self.bank.bytes_per_scene(),
            "nerf_total": self.bank.total_bytes(),
            "method_total": self.bank.total_bytes(),
        }


class Mapping(ContinualMethod):
    """Voxel-map pseudo-labels (GI+ML) with replay of stored image/label pairs."""

    name = "mapping"

    def __init__(self, context: MethodContext, voxel: VoxelMapConfig | None = None):
        super().__init__(context)
        self.voxel = voxel or VoxelMapConfig()
        self.memories: list[MappingMemory] = []

    def step(self, model: SegmentationNet, scene: Scene) -> dict[str, Any]:
        cfg = self.config
        frames = scene.train_frames
        t0 = time.perf_counter()
        # As ours: predict with the scene's statistics.
        self._adabn(model, scene, self.context.pretrain)
        predictions = predict_frames(model, frames, device=cfg.seg.device)
        t1 = time.perf_counter()
        voxel_map = build_voxel_map(scene, predictions, self.voxel)
        labels = render_map_labels(voxel_map, scene, [f.name for f in frames])
        t2 = time.perf_counter()
        previous = [m for m in self.memories if m.scene != scene.name]
        replay = mapping_replay_buffer(previous, cfg.replay.buffer_size) if previous else None
        losses = finetune_on_labels(
            model,
            [f.color for f in frames],
            [labels[f.name] for f in frames],
            cfg,
            cfg.seg.epochs,
            replay,
            self.context.pretrain,
        )
        self._adabn(model, scene, self.context.pretrain)
        t3 = time.perf_counter()
        memory = mapping_memory(scene, labels, voxel_map)
        self.memories = [*previous, memory]
        return {
            "scene": scene.name,
            "method": self.name,
            "prediction_miou": label_miou(predictions, scene),
            "pseudo_label_miou": label_miou(labels, scene),
            "num_voxels": voxel_map.num_voxels,
            "history": [{"epoch": k + 1, "loss": v} for k, v in enumerate(losses)],
            "replay": replay.per_scene() if replay is not None else {},
            "replay_bytes": replay.nbytes() if replay is not None else 0,
            "stored_bytes": memory.footprint().total_bytes,
            "seconds": {"predict": t1 - t0, "fusion": t2 - t1, "finetune": t3 - t2},
        }

    def memory_bytes(self) -> dict[str, Any]:
        raw = {m.scene: m.footprint().total_bytes for m in self.memories}
        png = {m.scene: m.footprint(".png").total_bytes for m in self.memories}
        return {
            "mapping_per_scene": raw,
            "mapping_total": sum(raw.values()),
            "mapping_total_png": sum(png.values()),
            "method_total": sum(raw.values()),
        }

    def settings(self) -> dict[str, Any]:
        return {"voxel_size": self.voxel.voxel_size, "search_radius": self.voxel.search_radius}


# The ``tiny`` preset (tests) averages the teacher over flips at scale 1 only.
TINY_COTTA_SCALES = (1.0,)


def cotta_config(config: AdaptConfig) -> CoTTAConfig:
    """CoTTA's settings for a run: the paper's under the ``paper`` preset, its CPU variant
    (three scales instead of six) under ``cpu``, one scale under ``tiny``; seed and device
    follow the segmentation budget."""
    if config.preset == "paper":
        base = CoTTAConfig()
    elif config.preset == "tiny":
        base = CoTTAConfig(scales=TINY_COTTA_SCALES)
    else:
        base = CoTTAConfig.cpu()
    return dataclasses.replace(base, seed=config.seg.seed, device=config.seg.device)


class CoTTAMethod(ContinualMethod):
    """One CoTTA instance across the sequence; its teacher is the reported network."""

    name = "cotta"
    reestimates_batchnorm = False  # reports its EMA teacher, never re-estimates statistics

    def __init__(self, context: MethodContext, settings: CoTTAConfig | None = None):
        super().__init__(context)
        self.cotta_settings = settings or cotta_config(context.config)
        self.cotta: CoTTA | None = None

    def step(self, model: SegmentationNet, scene: Scene) -> dict[str, Any]:
        if self.cotta is None:
            self.cotta = CoTTA(model, self.cotta_settings)
        elif self.cotta.student is not model:
            raise ValueError("CoTTA: every step of a run must adapt the same network")
        t0 = time.perf_counter()
        frames = scene.train_frames
        labels = self.cotta.adapt(frames)
        return {
            "scene": scene.name,
            "method": self.name,
            # the teacher's gated online labels, each made before that image's update
            "pseudo_label_miou": label_miou(
                {f.name: lab for f, lab in zip(frames, labels, strict=True)}, scene
            ),
            "online_steps": self.cotta.steps,
            "last_loss": self.cotta.last_loss,
            "seconds": {"online": time.perf_counter() - t0},
        }

    def reported(self, model: SegmentationNet) -> nn.Module:
        return self.cotta.teacher if self.cotta is not None else model

    def memory_bytes(self) -> dict[str, Any]:
        if self.cotta is None:
            return {"method_total": 0}
        fp = self.cotta.footprint()
        return {
            "cotta_teacher": fp.teacher_bytes,
            "cotta_source": fp.source_bytes,
            "cotta_optimizer": fp.optimizer_bytes,
            "method_total": fp.extra_copies_bytes,
        }

    def settings(self) -> dict[str, Any]:
        return dataclasses.asdict(self.cotta_settings)


class SelfTraining(ContinualMethod):
    """The lower bound: fine-tune on the network's own predictions, no NeRF, no replay."""

    name = "finetune"

    def step(self, model: SegmentationNet, scene: Scene) -> dict[str, Any]:
        cfg = self.config
        frames = scene.train_frames
        t0 = time.perf_counter()
        self._adabn(model, scene, None)  # as ours: predict with the scene's statistics
        predictions = predict_frames(model, frames, device=cfg.seg.device)
        losses = finetune_on_labels(
            model,
            [f.color for f in frames],
            [predictions[f.name] for f in frames],
            cfg,
            cfg.seg.epochs,
        )
        self._adabn(model, scene, None)
        miou = label_miou(predictions, scene)
        return {
            "scene": scene.name,
            "method": self.name,
            "prediction_miou": miou,
            "pseudo_label_miou": miou,
            "history": [{"epoch": k + 1, "loss": v} for k, v in enumerate(losses)],
            "seconds": {"finetune": time.perf_counter() - t0},
        }


def pretrain_context(
    pretrain_scenes: Sequence[Scene], config: AdaptConfig
) -> tuple[PretrainReplay | None, float | None]:
    """The replayed slice of the pre-training data, and the entropy of the pre-training
    labels that the collapse guard falls back to (both ``None`` without pre-training scenes)."""
    if not pretrain_scenes:
        return None, None
    replay = PretrainReplay.from_scenes(
        pretrain_scenes, config.replay.pretrain_fraction, config.replay.seed
    )
    prior = label_entropy(
        f.labels[NYU40_FOLDER]
        for s in pretrain_scenes
        for f in s.train_frames
        if NYU40_FOLDER in f.labels
    )
    return replay, prior


_CLASSES: dict[str, type[ContinualMethod]] = {
    cls.name: cls for cls in (Ours, Mapping, CoTTAMethod, SelfTraining)
}


def check_method(name: str, allowed: Sequence[str] = METHODS, field: str = "method") -> str:
    """``name`` if it is one of ``allowed``, else an input error naming ``field``."""
    if name not in allowed:
        raise CSAInputError(field, f"unknown method {name!r} (choose from {', '.join(allowed)})")
    return name


def make_method(name: str, context: MethodContext) -> ContinualMethod:
    """The method called ``name`` (one of :data:`METHODS`)."""
    return _CLASSES[check_method(name)](context)


def one_step(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    method: str,
    out: str | Path,
    pretrain: PretrainReplay | None = None,
    prior_entropy: float | None = None,
) -> tuple[dict[str, Any], nn.Module]:
    """Adapt ``model`` (in place) to one scene with ``method``: one of :data:`METHODS`, or
    ``gi_nl``/``ni_nl``/``joint`` for ours in that mode. Returns the step's record with the
    val/train mIoU ``before`` and ``after`` (empty without ground truth), and the reported
    network (the teacher for CoTTA, ``model`` otherwise)."""
    check_method(method, (*METHODS, *MODES))
    if method in MODES:
        config = copy.deepcopy(config)
        config.mode = method
        name = "ours"
    else:
        name = method
    runner = make_method(name, MethodContext(config, Path(out), pretrain, prior_entropy))
    before = evaluate(model, scene, config.seg.device)
    record = runner.step(model, scene)
    reported = runner.reported(model)
    record["method"] = method
    record["mode"] = config.mode if name == "ours" else None
    record["before"] = before
    record["after"] = evaluate(reported, scene, config.seg.device)
    record["memory_bytes"] = runner.memory_bytes()
    record["method_settings"] = runner.settings()
    return record, reported
