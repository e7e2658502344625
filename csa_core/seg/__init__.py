"""Segmentation networks: models, checkpoints, augmentation, training, prediction and AdaBN.

Names are imported lazily, so ``csa_core.seg.config`` (and the command line that reads its
defaults) loads without torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "adabn": ("adapt_batchnorm", "batchnorm_layers", "recompute_batchnorm"),
    "checkpoint": ("ModelCard", "load_checkpoint", "read_model_card", "save_checkpoint"),
    "config": (
        "ARCH_NAMES", "DEFAULT_ARCH", "PAPER_ADAPT_BATCH_SIZE", "PAPER_ADAPT_LR", "PAPER_ARCH",
        "AugmentConfig", "PretrainConfig", "TrainConfig",
    ),
    "dataset": ("SegmentationDataset",),
    "losses": ("IGNORE_INDEX", "nyu40_to_target", "segmentation_loss"),
    "models": ("ARCHS", "SegmentationNet", "build_model"),
    "predict": ("evaluate_scene", "predict_labels", "predict_logits", "predict_scene"),
    "pretraining": ("pretrain",),
    "train": ("SegmentationTrainer", "TrainResult", "train_segmentation"),
    "transforms": ("JointAugment",),
}  # fmt: skip
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'csa_core.seg' has no attribute {name!r}")
    return getattr(importlib.import_module(f"csa_core.seg.{module}"), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
