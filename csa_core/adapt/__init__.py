"""Adaptation without labels: NeRF pseudo-labels, fine-tuning and joint 2D-3D training,
NeRF memory bank and replay, the continual driver, and the collapse guard."""

from csa_core.adapt.collapse import CollapseReport, GuardDecision, detect_collapse, label_entropy
from csa_core.adapt.config import AdaptConfig, preset
from csa_core.adapt.continual import ContinualResult, format_table, run_continual
from csa_core.adapt.finetune import OneStepResult, adapt_one_step
from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.pseudo_labels import PseudoLabels, make_pseudo_labels
from csa_core.adapt.replay import MixedBatchSampler, PretrainReplay, ReplayBuffer, split_buffer

__all__ = [
    "AdaptConfig",
    "CollapseReport",
    "ContinualResult",
    "GuardDecision",
    "MemoryBank",
    "MixedBatchSampler",
    "OneStepResult",
    "PretrainReplay",
    "PseudoLabels",
    "ReplayBuffer",
    "adapt_one_step",
    "detect_collapse",
    "format_table",
    "label_entropy",
    "make_pseudo_labels",
    "preset",
    "run_continual",
    "split_buffer",
]
