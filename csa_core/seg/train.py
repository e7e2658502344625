"""Supervised training of segmentation networks: pre-training now, adaptation later.

:class:`SegmentationTrainer` owns the optimiser and the learning-rate schedule and takes one
step or one epoch at a time, so joint 2D-3D training can interleave network epochs with NeRF
updates. :func:`train_segmentation` is the whole loop: epochs, per-epoch log line, validation
mIoU and the best checkpoint.
"""

from __future__ import annotations

import copy
import itertools
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Sampler
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from csa_core.device import resolve_device
from csa_core.eval.miou import ConfusionMatrix
from csa_core.progress import ProgressCallback
from csa_core.seg.adabn import recompute_batchnorm
from csa_core.seg.checkpoint import ModelCard, save_checkpoint
from csa_core.seg.config import TrainConfig
from csa_core.seg.dataset import SegmentationDataset
from csa_core.seg.losses import segmentation_loss
from csa_core.seg.models import SegmentationNet
from csa_core.seg.predict import predict_labels

log = logging.getLogger(__name__)

# Batches between progress reports inside an epoch: a long epoch stays cancellable.
BATCH_PROGRESS_EVERY = 10


def lr_factor(
    schedule: str, step: int, total_steps: int, poly_power: float = 0.9, final: float = 0.0
) -> float:
    """Multiplier of the initial learning rate at ``step`` of ``total_steps``: a decaying
    schedule goes from 1 to ``final`` (the final rate as a fraction of the first)."""
    t = min(step / max(total_steps, 1), 1.0)
    if schedule == "poly":
        decay = (1.0 - t) ** poly_power
    elif schedule == "linear":
        decay = 1.0 - t
    elif schedule == "cosine":
        decay = 0.5 * (1.0 + math.cos(math.pi * t))
    else:
        return 1.0
    return final + (1.0 - final) * decay


class SegmentationTrainer:
    """Adam steps on a segmentation network with a per-step decaying learning rate."""

    def __init__(self, model: SegmentationNet, config: TrainConfig, total_steps: int):
        self.model = model
        self.config = config
        self.total_steps = max(1, total_steps)
        self.device = resolve_device(config.device)
        model.to(self.device)
        self.optimizer = torch.optim.Adam(
            model.parameters(), lr=config.lr, weight_decay=config.weight_decay
        )
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer,
            lambda s: lr_factor(
                config.schedule,
                s,
                self.total_steps,
                config.poly_power,
                config.final_lr / config.lr,
            ),
        )
        self.steps_done = 0
        self.images_seen = 0

    @property
    def lr(self) -> float:
        return float(self.optimizer.param_groups[0]["lr"])

    def step(self, images: Tensor, labels: Tensor) -> float:
        """One optimiser step on a batch: (B, 3, H, W) floats in [0, 1], (B, H, W) NYU40 ids."""
        self.model.train()
        images, labels = images.to(self.device), labels.to(self.device)
        loss = segmentation_loss(self.model(images), labels)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"training loss became {loss.item()} at step {self.steps_done}; lower the "
                "learning rate"
            )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.scheduler.step()
        self.steps_done += 1
        self.images_seen += images.shape[0]
        return float(loss.detach())

    def recompute_batchnorm(
        self, dataset: Dataset[tuple[Tensor, Tensor]], generator: torch.Generator | None = None
    ) -> int:
        """Recompute BatchNorm statistics on up to ``config.precise_bn_images`` images of
        ``dataset``."""
        limit = self.config.precise_bn_images
        n = len(dataset)  # type: ignore[arg-type]
        if limit <= 0 or n < 2:
            return 0
        batch_size = min(16, n)
        loader = DataLoader(
            dataset,
            batch_size=batch_size,
            shuffle=True,
            drop_last=n > batch_size,
            generator=generator,
        )
        batches = (images for images, _ in itertools.islice(loader, math.ceil(limit / batch_size)))
        return recompute_batchnorm(self.model, batches, self.device)

    def run_epoch(
        self,
        batches: Iterable[tuple[Tensor, Tensor]],
        desc: str = "train",
        on_batch: Callable[[int, float], None] | None = None,
    ) -> float:
        """Steps over every batch with a progress bar; returns the mean loss (NaN if none).

        ``on_batch(batches done, mean loss so far)`` is called after every step; what it
        raises stops the epoch there.
        """
        total, count = 0.0, 0
        bar = tqdm(
            batches,
            desc=desc,
            leave=False,
            dynamic_ncols=True,
            disable=None if self.config.progress else True,
        )
        for images, labels in bar:
            total += self.step(images, labels)
            count += 1
            bar.set_postfix(loss=f"{total / count:.3f}", lr=f"{self.lr:.1e}")
            if on_batch is not None:
                on_batch(count, total / count)
        return total / count if count else float("nan")


@dataclass
class EpochLog:
    epoch: int
    train_loss: float
    lr: float
    seconds: float
    val_miou: dict[str, float] | None = None
    score: float | None = None


@dataclass
class TrainResult:
    """What a training run did: per-epoch log, the best epoch and its validation score."""

    history: list[EpochLog] = field(default_factory=list)
    best_epoch: int = 0
    best_score: float | None = None
    best_val_miou: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    images_seen: int = 0
    checkpoint: Path | None = None
    card: ModelCard | None = None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["checkpoint"] = str(self.checkpoint) if self.checkpoint else None
        return d


def seed_everything(seed: int) -> torch.Generator:
    """Seed torch's global RNG (initialisation, augmentation) and return a shuffling generator."""
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def validation_scores(
    model: SegmentationNet,
    val_sets: Mapping[str, SegmentationDataset],
    batch_size: int = 16,
    device: str | torch.device | None = None,
) -> dict[str, float]:
    """mIoU of the model on each validation set (its stored images, never augmented)."""
    scores: dict[str, float] = {}
    for name, ds in val_sets.items():
        matrix = ConfusionMatrix()
        if len(ds):
            for pred, gt in zip(
                predict_labels(model, ds.images, batch_size, device), ds.labels, strict=True
            ):
                matrix.update(pred, gt)
        scores[name] = matrix.miou()
    return scores


def _mean_score(scores: Mapping[str, float]) -> float | None:
    finite = [v for v in scores.values() if math.isfinite(v)]
    return sum(finite) / len(finite) if finite else None


def _batch_reporter(
    on_progress: ProgressCallback | None, epoch: int, epochs: int, n_batches: int
) -> Callable[[int, float], None] | None:
    """Reports every ``BATCH_PROGRESS_EVERY`` batches of an epoch but its last (the epoch's
    own report follows that one)."""
    if on_progress is None:
        return None

    def report(done: int, loss: float) -> None:
        if done % BATCH_PROGRESS_EVERY == 0 and done < n_batches:
            on_progress(
                f"epoch {epoch}/{epochs}  batch {done}/{n_batches}  loss {loss:.4f}",
                (epoch - 1 + done / n_batches) / epochs,
            )

    return report


def train_segmentation(
    model: SegmentationNet,
    train_set: Dataset[tuple[Tensor, Tensor]],
    config: TrainConfig | None = None,
    val_sets: Mapping[str, SegmentationDataset] | None = None,
    checkpoint: str | Path | None = None,
    card: ModelCard | None = None,
    batch_sampler: Sampler[list[int]] | None = None,
    on_progress: ProgressCallback | None = None,
) -> TrainResult:
    """Train ``model`` on ``train_set`` and keep the best weights.

    Each epoch shuffles ``train_set`` (seeded) into batches of ``config.batch_size``, dropping
    a last incomplete batch when there is more than one batch (a batch of one breaks
    BatchNorm); ``batch_sampler`` replaces that, e.g. to mix replay and current data in fixed
    proportions. Validation scores each set of ``val_sets`` separately and ranks epochs by
    their mean mIoU; without validation sets the last epoch is the best. On return the model
    holds the best weights, in eval mode, and ``checkpoint`` (if given) has them with ``card``
    completed by the training config and scores.

    ``on_progress(message, fraction)`` (:mod:`csa_core.progress`) is called after every epoch
    (before its checkpoint is written) and every ``BATCH_PROGRESS_EVERY`` batches within one.
    What it raises propagates unchanged and stops training at once: no checkpoint is
    written after it, and the model keeps the weights of the interrupted step.
    """
    config = config or TrainConfig()
    val_sets = dict(val_sets or {})
    if len(train_set) == 0:  # type: ignore[arg-type]
        raise ValueError("train_segmentation: the training set is empty")
    generator = seed_everything(config.seed)
    if batch_sampler is not None:
        loader = DataLoader(train_set, batch_sampler=batch_sampler)
    else:
        n = len(train_set)  # type: ignore[arg-type]
        drop_last = n > config.batch_size
        loader = DataLoader(
            train_set,
            batch_size=config.batch_size,
            shuffle=True,
            drop_last=drop_last,
            generator=generator,
        )
    trainer = SegmentationTrainer(model, config, total_steps=config.epochs * len(loader))
    bn_generator = torch.Generator().manual_seed(config.seed + 1)
    result = TrainResult()
    best_state: dict[str, Tensor] | None = None
    start = time.perf_counter()
    card = card or ModelCard.for_model(model)

    def keep_best(epoch: int, score: float | None, per_set: dict[str, float] | None) -> None:
        nonlocal best_state
        result.best_epoch, result.best_score, result.best_val_miou = (
            epoch,
            score,
            dict(per_set or {}),
        )
        best_state = copy.deepcopy(model.state_dict())
        result.seconds = time.perf_counter() - start
        if checkpoint is not None:
            result.card = save_checkpoint(checkpoint, model, _completed_card(card, config, result))
            result.checkpoint = Path(checkpoint)

    with logging_redirect_tqdm():
        for epoch in range(1, config.epochs + 1):
            t0 = time.perf_counter()
            loss = trainer.run_epoch(
                loader,
                desc=f"epoch {epoch}/{config.epochs}",
                on_batch=_batch_reporter(on_progress, epoch, config.epochs, len(loader)),
            )
            result.images_seen = trainer.images_seen
            entry = EpochLog(epoch=epoch, train_loss=loss, lr=trainer.lr, seconds=0.0)
            last = epoch == config.epochs
            scoring = bool(val_sets) and (epoch % config.val_every == 0 or last)
            if scoring or last:
                trainer.recompute_batchnorm(train_set, bn_generator)
            if scoring:
                entry.val_miou = validation_scores(model, val_sets, device=trainer.device)
                entry.score = _mean_score(entry.val_miou)
            entry.seconds = time.perf_counter() - t0
            result.history.append(entry)
            improved = entry.score is not None and (
                result.best_score is None or entry.score > result.best_score
            )
            line = f"epoch {epoch}/{config.epochs}  loss {loss:.4f}  lr {entry.lr:.2e}"
            if entry.score is not None:
                line += f"  val mIoU {100 * entry.score:.1f}%"
            log.info(line + f"  {entry.seconds:.1f}s" + ("  (best)" if improved else ""))
            if on_progress is not None:
                on_progress(line, epoch / config.epochs)
            if improved or (last and best_state is None):
                keep_best(epoch, entry.score, entry.val_miou)
    assert best_state is not None
    model.load_state_dict(best_state)
    model.eval()
    result.seconds = time.perf_counter() - start
    if checkpoint is not None:
        result.card = save_checkpoint(checkpoint, model, _completed_card(card, config, result))
    return result


def _completed_card(card: ModelCard, config: TrainConfig, result: TrainResult) -> ModelCard:
    merged = copy.deepcopy(card)
    merged.train_config = {**merged.train_config, "optimizer": "adam", **asdict(config)}
    merged.metrics = {
        **merged.metrics,
        "best_epoch": result.best_epoch,
        "val_miou": result.best_score,
        "val_miou_per_set": result.best_val_miou,
        "epochs_run": len(result.history),
        "train_seconds": round(result.seconds, 2),
        "images_seen": result.images_seen,
    }
    return merged
