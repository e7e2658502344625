"""The methods one continual run can use, behind one small interface (docs/method.md "Baselines").

:func:`csa_core.adapt.continual.run_continual` owns the protocol: the scenes and their order,
R and b, the continual metrics, ``results.json``. :func:`csa_core.adapt.step.continual_step`
owns a step: it calls the method, then pools BatchNorm statistics; what the run keeps between
steps (the NeRF memory bank, the BatchNorm records, the pre-training slice) is its
:class:`ContinualState`. A method owns what happens inside one step and
the memory only it keeps, so every method is scored by the same code on the same views:

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
- ``ours-pretrain-replay`` and ``ours-novel-views``: the paper's two other rows of ours in
  Tab. 3, "Ours (I_pre replay only)" (no replay buffer: only the pre-training slice) and
  "Ours (novel viewpoints)" (the buffer rendered at novel viewpoints). Each is ``ours`` with
  the replay fields of :data:`OURS_VARIANTS` set on the run's config (:func:`method_config`).

Mapping and the lower bound train with the same loop as ours (Adam, batch composition with
the pre-training slice where there is one), so a difference in R comes from the labels and
the memory, not from the optimiser. AdaBN (``AdaptConfig.adabn``, placed by
``adabn_placement``) applies to every method by one rule, CoTTA included, so a comparison
can be made with it on and off: with the ``paper`` placement only a network trained on
rendered images gets it, so the baselines, which train on camera images, get none.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
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
from csa_core.adapt.bn_memory import BatchNormMemory
from csa_core.adapt.collapse import label_entropy
from csa_core.adapt.config import MODES, AdaptConfig
from csa_core.adapt.finetune import (
    adabn_slice,
    apply_adabn,
    finetune_on_labels,
)
from csa_core.adapt.memory_bank import NerfMemory
from csa_core.adapt.modes import adapt_one_step
from csa_core.adapt.pseudo_labels import label_miou, predict_frames
from csa_core.adapt.replay import PretrainReplay, ReplayBuffer
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.overrides import apply_overrides
from csa_core.progress import ProgressCallback, notify
from csa_core.seg.models import SegmentationNet

# What a step's record says when our method banked no NeRF, per guard decision.
NOT_BANKED = {
    "skip": (
        "the collapse guard skipped the scene: no NeRF banked, later steps replay nothing of it"
    ),
    "fallback_predictions": (
        "the collapse guard rejected the NeRF's labels and the network trained on its own "
        "predictions: no NeRF banked, later steps replay nothing of this scene"
    ),
}

# The paper's Tab. 3 rows of ours beside "ours" (training viewpoints): the replay fields each
# sets on the run's config, through the one override path (csa_core.overrides).
OURS_VARIANTS: dict[str, tuple[str, ...]] = {
    "ours-pretrain-replay": ("replay.buffer_size=0",),  # "Ours (I_pre replay only)"
    "ours-novel-views": ("replay.views=novel",),  # "Ours (novel viewpoints)"
}
# Methods of the continual protocol; "ours" (and its variants) runs config.mode.
METHODS: tuple[str, ...] = ("ours", "mapping", "cotta", "finetune", *OURS_VARIANTS)
# Methods of the one-step protocol: our three modes by name, then the baselines.
ONE_STEP_METHODS: tuple[str, ...] = (*MODES, "mapping", "cotta", "finetune")


class ContinualMethod:
    """One method of the continual protocol, with the run's ``config``. ``step`` adapts
    ``model`` in place to one scene, using and updating the run's ``state``, and returns the
    step's record for ``results.json`` (``trained: False`` when the scene was skipped);
    ``reported`` is the network that is scored and saved; ``memory_bytes`` is what the
    method stores after the steps so far, with ``method_total`` the bytes that count in the
    comparison of methods. Call ``step`` through :func:`csa_core.adapt.step.continual_step`."""

    name: ClassVar[str] = ""

    def __init__(self, config: AdaptConfig):
        self.config = config

    def step(
        self,
        state: ContinualState,
        model: SegmentationNet,
        scene: Scene,
        on_progress: ProgressCallback | None = None,
    ) -> dict[str, Any]:
        raise NotImplementedError

    def reported(self, model: SegmentationNet) -> nn.Module:
        return model

    def memory_bytes(self, state: ContinualState) -> dict[str, Any]:
        return {"method_total": 0}

    def settings(self) -> dict[str, Any]:
        """Settings of the method beyond the AdaptConfig (recorded with the results)."""
        return {}

    def _adabn(
        self,
        model: nn.Module,
        scene: Scene,
        pretrain: PretrainReplay | None,
        before_labels: bool = False,
    ) -> None:
        """AdaBN on the scene's camera images, for a baseline (trained on camera images):
        before the network labels the scene (``before_labels``) or at the end of a step,
        where ``config.adabn`` and ``config.adabn_placement`` put it."""
        wanted = (
            self.config.adabn_before_labels
            if before_labels
            else self.config.adabn_after_training(rendered=False)
        )
        if wanted:
            apply_adabn(
                model,
                [f.color for f in scene.train_frames],
                adabn_slice(self.config, pretrain),
                self.config.seg.seed,
                self.config.seg.device,
            )


class CSAMethod(ContinualMethod):
    """Continual semantic adaptation, the method ``ours``: NeRF pseudo-labels in
    ``config.mode`` with replay from the run's NeRF memory bank (``state.bank``): the earlier
    scenes' NeRFs as stored, i.e. read back from their checkpoints. The scene's NeRF joins
    the bank only when the collapse guard accepted its labels: after a ``skip`` or a
    ``fallback_predictions`` nothing is banked (the record's ``nerf_banked`` is false and
    ``not_banked`` says why), so later steps replay nothing of the scene. A joint training
    the guard stopped banks the NeRF as restored to its last accepted state."""

    name = "ours"

    def step(
        self,
        state: ContinualState,
        model: SegmentationNet,
        scene: Scene,
        on_progress: ProgressCallback | None = None,
    ) -> dict[str, Any]:
        cfg = self.config
        bank = state.bank
        if bank is None:
            raise ValueError("ours: the continual state has no NeRF memory bank")
        t0 = time.perf_counter()
        previous = [n for n in bank.scenes if n != scene.name]
        replay = None
        if previous and cfg.replay.buffer_size > 0:
            notify(on_progress, f"rendering replay from {len(previous)} earlier scene(s)", 0.0)
            replay = ReplayBuffer.from_memory_bank(
                bank,
                cfg.replay.buffer_size,
                cfg.replay.views,
                previous,
                cfg.replay.max_render_samples,
                device=cfg.seg.device,
                draw=cfg.replay.draw,
                seed=cfg.replay.seed,
            )
        t_replay = time.perf_counter() - t0
        result = adapt_one_step(
            model,
            scene,
            cfg,
            replay,
            state.pretrain,
            prior_entropy=state.prior_entropy,
            evaluate_before=False,
            on_progress=on_progress,
        )
        action = result.decisions[0].action if result.decisions else "continue"
        banked = result.nerf is not None and result.trained and action == "continue"
        if banked:
            bank.add(scene.name, result.nerf)  # type: ignore[arg-type]
        record = result.to_dict()
        record["method"] = self.name
        record["nerf_banked"] = banked
        if not banked:
            record["not_banked"] = NOT_BANKED.get(action, action)
        record["seconds"] = {**record["seconds"], "replay_render": t_replay}
        record["replay"] = replay.per_scene() if replay is not None else {}
        record["replay_bytes"] = replay.nbytes() if replay is not None else 0
        record["nerf_bytes"] = bank.bytes_per_scene().get(scene.name, 0) if banked else 0
        return record

    def memory_bytes(self, state: ContinualState) -> dict[str, Any]:
        per_scene = state.bank.bytes_per_scene() if state.bank is not None else {}
        total = sum(per_scene.values())
        return {"nerf_per_scene": per_scene, "nerf_total": total, "method_total": total}


def method_config(name: str, config: AdaptConfig) -> AdaptConfig:
    """The config a run of method ``name`` runs with: for a variant of ours
    (:data:`OURS_VARIANTS`), a copy of ``config`` with the variant's replay fields set (they
    have the last word, over ``--set``); ``config`` itself for every other method."""
    items = OURS_VARIANTS.get(name)
    if not items:
        return config
    return apply_overrides(copy.deepcopy(config), items, flag=f"method {name}")


class CSAPretrainReplay(CSAMethod):
    """The paper's "Ours (I_pre replay only)" (Tab. 3): ours without the replay buffer; the
    network still trains with the pre-training slice. It banks its NeRFs as ours does (the
    service renders from them), though no later step of it replays them."""

    name = "ours-pretrain-replay"

    def __init__(self, config: AdaptConfig):
        super().__init__(method_config(self.name, config))


class CSANovelViews(CSAMethod):
    """The paper's "Ours (novel viewpoints)" (Tab. 3): ours with the replay buffer rendered at
    novel viewpoints, midway between consecutive training poses (docs/method.md "Remember")."""

    name = "ours-novel-views"

    def __init__(self, config: AdaptConfig):
        super().__init__(method_config(self.name, config))


class Mapping(ContinualMethod):
    """Voxel-map pseudo-labels (GI+ML) with replay of stored image/label pairs."""

    name = "mapping"

    def __init__(self, config: AdaptConfig, voxel: VoxelMapConfig | None = None):
        super().__init__(config)
        self.voxel = voxel or VoxelMapConfig()
        self.memories: list[MappingMemory] = []

    def step(
        self,
        state: ContinualState,
        model: SegmentationNet,
        scene: Scene,
        on_progress: ProgressCallback | None = None,
    ) -> dict[str, Any]:
        cfg = self.config
        frames = scene.train_frames
        t0 = time.perf_counter()
        # As ours: predict with the scene's statistics where the placement says so.
        self._adabn(model, scene, state.pretrain, before_labels=True)
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
            state.pretrain,
            on_progress,
        )
        self._adabn(model, scene, state.pretrain)
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

    def memory_bytes(self, state: ContinualState) -> dict[str, Any]:
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


def cotta_config(config: AdaptConfig) -> CoTTAConfig:
    """CoTTA's settings for a run: the paper's constants with the run's augmentation
    (``config.cotta``: six scales in ``paper``, three in ``cpu``, one in ``tiny``); seed and
    device follow the segmentation budget."""
    return CoTTAConfig(
        scales=config.cotta.scales,
        flip=config.cotta.flip,
        seed=config.seg.seed,
        device=config.seg.device,
    )


class CoTTAMethod(ContinualMethod):
    """One CoTTA instance across the sequence; its teacher is the reported network.

    AdaBN applies to CoTTA as to the other methods: with ``config.adabn`` the teacher (the
    network that is scored, pooled and saved) and the student re-estimate their statistics on
    the scene's camera images after the online pass, and where ``config.adabn_placement``
    also puts AdaBN before the network labels a scene, they do so before the pass too (the
    teacher makes the pass's pseudo-labels, the student is trained with its statistics).
    The frozen source network keeps the pre-trained statistics: it is CoTTA's anchor.
    """

    name = "cotta"

    def __init__(self, config: AdaptConfig, settings: CoTTAConfig | None = None):
        super().__init__(config)
        self.cotta_settings = settings or cotta_config(config)
        self.cotta: CoTTA | None = None

    def step(
        self,
        state: ContinualState,
        model: SegmentationNet,
        scene: Scene,
        on_progress: ProgressCallback | None = None,
    ) -> dict[str, Any]:
        if self.cotta is None:
            self.cotta = CoTTA(model, self.cotta_settings)
        elif self.cotta.student is not model:
            raise ValueError("CoTTA: every step of a run must adapt the same network")
        t0 = time.perf_counter()
        frames = scene.train_frames
        for net in (self.cotta.teacher, self.cotta.student):
            self._adabn(net, scene, state.pretrain, before_labels=True)
        t1 = time.perf_counter()
        labels = self.cotta.adapt(frames)
        t2 = time.perf_counter()
        for net in (self.cotta.teacher, self.cotta.student):
            self._adabn(net, scene, state.pretrain)
        return {
            "scene": scene.name,
            "method": self.name,
            # the teacher's gated online labels, each made before that image's update
            "pseudo_label_miou": label_miou(
                {f.name: lab for f, lab in zip(frames, labels, strict=True)}, scene
            ),
            "online_steps": self.cotta.steps,
            "last_loss": self.cotta.last_loss,
            "seconds": {
                "adabn": t1 - t0 + time.perf_counter() - t2,
                "online": t2 - t1,
            },
        }

    def reported(self, model: SegmentationNet) -> nn.Module:
        return self.cotta.teacher if self.cotta is not None else model

    def memory_bytes(self, state: ContinualState) -> dict[str, Any]:
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

    def step(
        self,
        state: ContinualState,
        model: SegmentationNet,
        scene: Scene,
        on_progress: ProgressCallback | None = None,
    ) -> dict[str, Any]:
        cfg = self.config
        frames = scene.train_frames
        t0 = time.perf_counter()
        self._adabn(model, scene, None, before_labels=True)  # as ours
        predictions = predict_frames(model, frames, device=cfg.seg.device)
        losses = finetune_on_labels(
            model,
            [f.color for f in frames],
            [predictions[f.name] for f in frames],
            cfg,
            cfg.seg.epochs,
            on_progress=on_progress,
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
    cls.name: cls
    for cls in (CSAMethod, Mapping, CoTTAMethod, SelfTraining, CSAPretrainReplay, CSANovelViews)
}


@dataclass
class ContinualState:
    """What a continual run keeps between steps.

    ``method``: the method with its own memory (:mod:`csa_core.adapt.methods`; it holds the
    run's :class:`~csa_core.adapt.config.AdaptConfig`). ``bank``: the NeRF memory bank of our
    method (any :class:`~csa_core.adapt.memory_bank.NerfMemory`; unused by the baselines).
    ``batchnorm``: the per-scene BatchNorm statistics, ``None`` when the run does not pool
    them. ``pretrain``: the replayed slice of the pre-training data; ``prior_entropy``: the
    class entropy of the pre-training labels, the collapse guard's fallback reference.
    """

    method: ContinualMethod
    bank: NerfMemory | None = None
    batchnorm: BatchNormMemory | None = None
    pretrain: PretrainReplay | None = None
    prior_entropy: float | None = None

    @property
    def config(self) -> AdaptConfig:
        return self.method.config

    @classmethod
    def start(
        cls,
        config: AdaptConfig,
        method: str = "ours",
        *,
        bank: NerfMemory | None = None,
        pretrain_scenes: Sequence[Scene] = (),
        batchnorm: BatchNormMemory | None = None,
    ) -> ContinualState:
        """The state of a run with ``method`` (one of :data:`~csa_core.adapt.methods.METHODS`)
        about to take its next step: ``bank`` holds the earlier scenes' NeRFs (our method
        needs one), ``batchnorm`` their BatchNorm records (a fresh memory when ``None``; used
        only when :func:`pools_batchnorm`), ``pretrain_scenes`` give the pre-training slice
        and the prior entropy."""
        runner = make_method(method, config)
        pretrain, prior = pretrain_context(pretrain_scenes, config)
        memory = None
        if pools_batchnorm(config):
            memory = batchnorm if batchnorm is not None else BatchNormMemory()
        return cls(runner, bank, memory, pretrain, prior)

    def memory_bytes(self) -> dict[str, Any]:
        """What the method stores after the steps so far (``method_total`` counts in the
        comparison of methods), and the BatchNorm records when the run pools them."""
        out = self.method.memory_bytes(self)
        if self.batchnorm is not None:
            out["batchnorm_statistics"] = self.batchnorm.nbytes()
        return out


def pools_batchnorm(config: AdaptConfig) -> bool:
    """Whether a run keeps per-scene BatchNorm statistics and runs with their mixture: with
    AdaBN (which every method's step ends with) and ``config.pool_batchnorm``."""
    return bool(config.adabn and config.pool_batchnorm)


def check_method(name: str, allowed: Sequence[str] = METHODS, field: str = "method") -> str:
    """``name`` if it is one of ``allowed``, else an input error naming ``field``."""
    if name not in allowed:
        raise CSAInputError(field, f"unknown method {name!r} (choose from {', '.join(allowed)})")
    return name


def make_method(name: str, config: AdaptConfig) -> ContinualMethod:
    """The method called ``name`` (one of :data:`METHODS`) for a run with ``config``."""
    return _CLASSES[check_method(name)](config)
