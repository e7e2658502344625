"""Adaptation without labels: NeRF pseudo-labels, fine-tuning and joint 2D-3D training,
NeRF memory bank and replay, the continual driver, and the collapse guard.

Names are imported lazily, so ``csa_core.adapt.config`` (and the command line that reads its
presets) loads without torch.
"""

from __future__ import annotations

from csa_core.lazy_exports import lazy_exports

_EXPORTS = {
    "collapse": ("CollapseReport", "GuardDecision", "detect_collapse", "label_entropy"),
    "config": ("AdaptConfig", "preset"),
    "continual": ("ContinualResult", "format_table", "run_continual"),
    "finetune": ("OneStepResult",),
    "modes": ("adapt_one_step",),
    "memory_bank": ("MemoryBank",),
    "pseudo_labels": ("PseudoLabels", "make_pseudo_labels"),
    "replay": ("MixedBatchSampler", "PretrainReplay", "ReplayBuffer", "split_buffer"),
    "methods": ("ContinualState",),
    "step": ("continual_step", "one_step"),
    "bn_memory": ("BatchNormMemory",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
