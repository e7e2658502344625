"""Segmentation networks: models, checkpoints, augmentation, training, prediction and AdaBN.

Names are imported lazily, so ``csa_core.seg.config`` (and the command line that reads its
defaults) loads without torch.
"""

from __future__ import annotations

from csa_core.lazy_exports import lazy_exports

_EXPORTS = {
    "adabn": ("adapt_batchnorm", "batchnorm_layers", "recompute_batchnorm"),
    "checkpoint": ("ModelCard", "load_checkpoint", "read_model_card", "save_checkpoint"),
    "config": (
        "ARCH_NAMES", "DEFAULT_ARCH", "PAPER_ARCH", "AugmentConfig", "PretrainConfig",
        "TrainConfig",
    ),
    "dataset": ("SegmentationDataset",),
    "losses": ("IGNORE_INDEX", "nyu40_to_target", "segmentation_loss"),
    "models": ("ARCHS", "SegmentationNet", "build_model"),
    "predict": ("evaluate_scene", "predict_labels", "predict_logits", "predict_scene"),
    "pretraining": ("pretrain",),
    "train": ("SegmentationTrainer", "TrainResult", "train_segmentation"),
    "transforms": ("JointAugment",),
}  # fmt: skip
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
