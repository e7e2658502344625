"""Fine-tuning on pseudo-labels, and the start every mode of a step shares (docs/method.md
"Adapt"); :func:`csa_core.adapt.modes.adapt_one_step` picks the mode.

Modes: ``gi_nl`` fine-tunes on the camera images with the NeRF's labels, ``ni_nl`` on the
NeRF's rendered images with its labels (:func:`finetune_adapt`), ``joint`` alternates network
and NeRF updates (:mod:`csa_core.adapt.joint`). Before scoring on camera images the
BatchNorm statistics are re-estimated on the scene's camera images (AdaBN), which matters
most after training on rendered ones. Replay pairs and the pre-training slice join the
batches as docs/method.md "Remember" says.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, default_collate

from csa_core.adapt.collapse import GuardDecision, detect_collapse, guard
from csa_core.adapt.config import AdaptConfig, NerfBudget
from csa_core.adapt.pseudo_labels import PseudoLabels, label_miou, make_pseudo_labels
from csa_core.adapt.replay import MixedBatchSampler, PretrainReplay, ReplayBuffer
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.nerf.model import SemanticNerf
from csa_core.progress import ProgressCallback, notify, sub_progress
from csa_core.seg.adabn import adapt_batchnorm
from csa_core.seg.config import AugmentConfig, TrainConfig
from csa_core.seg.dataset import SegmentationDataset
from csa_core.seg.models import SegmentationNet
from csa_core.seg.predict import evaluate_scene
from csa_core.seg.train import SegmentationTrainer
from csa_core.seg.transforms import JointAugment

log = logging.getLogger(__name__)

# Shares of one step's progress (``on_progress``): pseudo-labels (mostly the NeRF fit) up to
# PSEUDO_LABELS_DONE, training (epochs or joint rounds) up to TRAINING_DONE, then scoring.
PSEUDO_LABELS_DONE = 0.5
TRAINING_DONE = 0.95


def training_pairs(
    images: Sequence[np.ndarray],
    labels: Sequence[np.ndarray],
    replay: ReplayBuffer | None = None,
    pretrain: PretrainReplay | None = None,
    augment: AugmentConfig | None = None,
) -> tuple[SegmentationDataset, int, int]:
    """One dataset: the current scene's pairs, then the replay buffer (together the "current
    or buffer" part), then the pre-training slice. Returns it with the sizes of both parts."""
    imgs, labs = list(images), list(labels)
    if replay is not None:
        imgs += replay.images
        labs += replay.labels
    primary = len(imgs)
    if pretrain is not None:
        imgs += pretrain.images
        labs += pretrain.labels
    transform = JointAugment(augment) if augment is not None else None
    return SegmentationDataset(imgs, labs, transform=transform), primary, len(imgs) - primary


class SegFinetuner:
    """Adam on the network over mixed batches, one epoch (pass over the current + buffer
    pairs) at a time, with one learning-rate schedule across all epochs of the step."""

    def __init__(
        self, model: SegmentationNet, config: AdaptConfig, epochs: int, batches_per_epoch: int
    ):
        seg = config.seg
        self.config = config
        self.train_config = TrainConfig(
            epochs=max(1, epochs),
            batch_size=seg.batch_size,
            lr=seg.lr,
            schedule=seg.schedule,
            seed=seg.seed,
            device=seg.device,
            progress=False,
            precise_bn_images=0,
        )
        self.trainer = SegmentationTrainer(
            model, self.train_config, total_steps=max(1, epochs * batches_per_epoch)
        )
        self.epochs_done = 0

    def batches(self, primary: int, secondary: int) -> MixedBatchSampler:
        """The index batches of the next epoch (``primary`` current-or-buffer items, then
        ``secondary`` pre-training items); seeds the epoch's augmentation draws."""
        r = self.config.replay
        per_batch = self.config.seg.batch_size
        pre = min(r.pretrain_per_batch, per_batch - 1) if secondary else 0
        sampler = MixedBatchSampler(
            primary,
            secondary,
            per_batch - pre,
            pre,
            seed=self.config.seg.seed + 1000 * self.epochs_done,
        )
        torch.manual_seed(self.config.seg.seed + self.epochs_done)  # augmentation draws
        return sampler

    def step(self, dataset: SegmentationDataset, batch: Sequence[int]) -> float:
        """One Adam step on the items ``batch`` of ``dataset`` (one of :meth:`batches`);
        returns its loss. Call :meth:`end_epoch` after the epoch's last batch."""
        images, labels = default_collate([dataset[i] for i in batch])
        return self.trainer.step(images, labels)

    def end_epoch(self) -> None:
        self.epochs_done += 1

    def epoch(self, dataset: SegmentationDataset, primary: int, secondary: int) -> float:
        """One pass; returns the mean loss."""
        sampler = self.batches(primary, secondary)
        loss = self.trainer.run_epoch(DataLoader(dataset, batch_sampler=sampler))
        self.epochs_done += 1
        return loss


def batches_per_epoch(primary: int, secondary: int, config: AdaptConfig) -> int:
    per_batch = config.seg.batch_size
    pre = min(config.replay.pretrain_per_batch, per_batch - 1) if secondary else 0
    return math.ceil(primary / (per_batch - pre))


def apply_adabn(
    model: SegmentationNet,
    camera_images: Sequence[np.ndarray],
    pretrain: PretrainReplay | None = None,
    seed: int = 0,
    device: str | None = None,
) -> int:
    """AdaBN on camera images: the scene's own and, when given, the pre-training slice
    (so earlier domains keep a say in the statistics; see ``AdaptConfig.adabn_mix_pretrain``)."""
    images = list(camera_images) + (list(pretrain.images) if pretrain is not None else [])
    if len(images) < 2:
        return 0
    return adapt_batchnorm(model, images, batch_size=16, device=device, seed=seed)


def adabn_only_scores(
    model: SegmentationNet, scenes: Sequence[Scene], seed: int = 0, device: str | None = None
) -> list[float]:
    """Per scene, the validation mIoU of ``model`` (not changed) with only its BatchNorm
    statistics re-estimated on that scene's training camera images: "AdaBN alone", the
    reference every method is compared with. Not a continual method: it is told which scene
    it is in, so nothing is forgotten and its mean is the ACC it would have."""
    import copy

    scores = []
    for scene in scenes:
        m = copy.deepcopy(model)
        apply_adabn(m, [f.color for f in scene.train_frames], seed=seed, device=device)
        scores.append(evaluate_scene(m, scene, "val", device=device).miou())
    return scores


def adabn_slice(config: AdaptConfig, pretrain: PretrainReplay | None) -> PretrainReplay | None:
    """The pre-training images AdaBN mixes in: the slice when the config asks for it."""
    return pretrain if config.adabn_mix_pretrain else None


def evaluate(model: SegmentationNet, scene: Scene, device: str | None = None) -> dict[str, float]:
    """mIoU on the scene's validation and training views; empty for a scene without ground
    truth, which is the product's normal case (labels are used only to score, never to train)."""
    if not any(NYU40_FOLDER in f.labels for f in scene.frames):
        return {}
    return {
        split: evaluate_scene(model, scene, split, device=device).miou()
        for split in ("val", "train")
    }


@dataclass
class OneStepResult:
    """What one adaptation step did and measured (mIoU as fractions)."""

    scene: str
    mode: str
    before: dict[str, float]
    after: dict[str, float]
    prediction_miou: float  # the previous network's labels on the training views
    pseudo_label_miou: float  # the NeRF's labels that trained the network (first fit)
    final_label_miou: float  # the NeRF's labels after the last joint round
    decisions: list[GuardDecision] = field(default_factory=list)
    history: list[dict[str, float]] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    trained: bool = True
    nerf: SemanticNerf | None = None
    # NeRF steps taken: "fit" (before the pseudo-labels), "semantic" (semantic head alone
    # after it) and "joint" (during joint training).
    nerf_steps: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scene": self.scene,
            "mode": self.mode,
            "before": self.before,
            "after": self.after,
            "prediction_miou": self.prediction_miou,
            "pseudo_label_miou": self.pseudo_label_miou,
            "final_label_miou": self.final_label_miou,
            "decisions": [d.to_dict() for d in self.decisions],
            "history": self.history,
            "seconds": self.seconds,
            "trained": self.trained,
            "nerf_steps": self.nerf_steps,
        }


def check_labels(
    stage: str,
    labels: Mapping[str, np.ndarray],
    pseudo: PseudoLabels,
    config: AdaptConfig,
    prior_entropy: float | None,
    in_joint: bool = False,
) -> GuardDecision:
    """Collapse check of ``labels`` against the previous model's predictions, and the guard's
    decision."""
    report = detect_collapse(labels, pseudo.predictions, config.collapse, prior_entropy)
    previous = detect_collapse(pseudo.predictions, None, config.collapse, prior_entropy)
    return guard(
        stage, report, config.collapse, previous_collapsed=previous.collapsed, in_joint=in_joint
    )


def finetune_on_labels(
    model: SegmentationNet,
    images: Sequence[np.ndarray],
    labels: Sequence[np.ndarray],
    config: AdaptConfig,
    epochs: int,
    replay: ReplayBuffer | None = None,
    pretrain: PretrainReplay | None = None,
    on_progress: ProgressCallback | None = None,
) -> list[float]:
    """Fine-tune on image/label pairs (plus replay) for ``epochs``; returns the epoch losses.
    ``on_progress`` (:mod:`csa_core.progress`) is called after every epoch."""
    dataset, primary, secondary = training_pairs(
        images, labels, replay, pretrain, config.seg.augment
    )
    tuner = SegFinetuner(model, config, epochs, batches_per_epoch(primary, secondary, config))
    losses: list[float] = []
    for k in range(1, epochs + 1):
        losses.append(tuner.epoch(dataset, primary, secondary))
        notify(on_progress, f"epoch {k}/{epochs}  loss {losses[-1]:.4f}", k / epochs)
    return losses


def step_nerf_budget(config: AdaptConfig, scene: Scene, mode: str | None = None) -> NerfBudget:
    """``config.nerf`` with the fit before the pseudo-labels in steps for ``scene``: its
    epochs (:meth:`~csa_core.adapt.config.NerfBudget.fit_steps`, in ``mode``, default
    ``config.mode``) times the scene's training views.
    :func:`~csa_core.adapt.config.nerf_config` of it is the NeRF config the step fits."""
    steps = config.nerf.fit_steps(mode or config.mode, len(scene.train_frames))
    return dataclasses.replace(config.nerf, prefit_steps=steps)


def begin_step(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    stage: str,
    prior_entropy: float | None,
    evaluate_before: bool,
    on_progress: ProgressCallback | None = None,
    pretrain: PretrainReplay | None = None,
) -> tuple[OneStepResult, PseudoLabels, dict[str, float]]:
    """The common start of every mode: score before (optional), re-estimate BatchNorm
    statistics on the scene's camera images (``config.adabn_before_labels``), fit the NeRF on
    the network's predictions (:func:`step_nerf_budget`), render pseudo-labels, check them
    for collapse at ``stage``. ``on_progress`` is the whole step's; this part reports up to
    ``PSEUDO_LABELS_DONE``.

    The AdaBN before predicting matters: a network trained from scratch on another domain
    labels a new scene with stale BatchNorm statistics far worse (measured on a synthetic
    office room: 26.6% mIoU on its training views with the source statistics, 33.3% with
    the scene's), and the NeRF can only fuse what the network predicts.
    """
    device = config.seg.device
    t0 = time.perf_counter()
    before = evaluate(model, scene, device) if evaluate_before else {}
    if config.adabn_before_labels:
        apply_adabn(
            model,
            [f.color for f in scene.train_frames],
            adabn_slice(config, pretrain),
            config.seg.seed,
            device,
        )
    t_eval = time.perf_counter() - t0
    budget = step_nerf_budget(config, scene)
    nerf, pseudo = make_pseudo_labels(
        model,
        scene,
        budget,
        device,
        sub_progress(on_progress, 0.0, PSEUDO_LABELS_DONE),
        color=config.trains_on_rendered_images,
    )
    seconds = {"evaluate": t_eval, **pseudo.seconds}
    decision = check_labels(stage, pseudo.labels, pseudo, config, prior_entropy)
    pseudo_miou = label_miou(pseudo.labels, scene)
    result = OneStepResult(
        scene=scene.name,
        mode=config.mode,
        before=before,
        after={},
        prediction_miou=label_miou(pseudo.predictions, scene),
        pseudo_label_miou=pseudo_miou,
        final_label_miou=pseudo_miou,
        decisions=[decision],
        nerf=nerf,
        nerf_steps={"fit": budget.prefit_steps, "semantic": budget.semantic_steps},
    )
    return result, pseudo, seconds


def finetune_adapt(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    replay: ReplayBuffer | None = None,
    pretrain: PretrainReplay | None = None,
    prior_entropy: float | None = None,
    evaluate_before: bool = True,
    on_progress: ProgressCallback | None = None,
) -> OneStepResult:
    """The fine-tuning modes' step (``gi_nl``, ``ni_nl``) of
    :func:`~csa_core.adapt.modes.adapt_one_step`: pseudo-labels from the NeRF fitted on the
    network's predictions (:func:`begin_step`), then ``config.seg.epochs`` of fine-tuning on
    them with the replay pairs and the pre-training slice."""
    device = config.seg.device
    result, pseudo, seconds = begin_step(
        model, scene, config, "pseudo_labels", prior_entropy, evaluate_before, on_progress, pretrain
    )
    decision = result.decisions[0]
    t1 = time.perf_counter()
    if decision.action == "skip":
        result.trained = False
    else:
        labels = pseudo.predictions if decision.action == "fallback_predictions" else pseudo.labels
        rendered = config.trains_on_rendered_images and decision.action == "continue"
        losses = finetune_on_labels(
            model,
            pseudo.images(rendered),
            [labels[n] for n in pseudo.names],
            config,
            config.seg.epochs,
            replay,
            pretrain,
            sub_progress(on_progress, PSEUDO_LABELS_DONE, TRAINING_DONE),
        )
        result.history = [{"epoch": k + 1, "loss": loss} for k, loss in enumerate(losses)]
        if config.adabn_after_training(rendered):
            apply_adabn(
                model, pseudo.images(False), adabn_slice(config, pretrain), config.seg.seed, device
            )
    seconds["finetune"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    result.after = evaluate(model, scene, device)
    seconds["evaluate"] += time.perf_counter() - t2
    result.seconds = seconds
    notify(on_progress, f"adapted to {scene.name}", 1.0)
    return result
