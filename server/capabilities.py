"""Which parts of the core library this build has, detected by import.

The service registers a job kind or endpoint whenever the core function behind it can be
imported, so a build without, say, ``csa_core.adapt`` still serves everything else and
answers ``adapt`` requests with 501 "not available in this build".
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass


@dataclass(frozen=True)
class Capability:
    """``functions`` are ``module:name`` pairs that must import and be callable."""

    name: str
    functions: tuple[str, ...]
    purpose: str


CAPABILITIES: dict[str, Capability] = {
    c.name: c
    for c in (
        Capability(
            "nerf",
            (
                "csa_core.nerf.fit:fit_semantic_nerf",
                "csa_core.nerf.checkpoint:save_checkpoint",
                "csa_core.nerf.checkpoint:load_checkpoint",
                "csa_core.nerf.render:render_image",
            ),
            "NeRF fitting, memory bank and rendering",
        ),
        Capability(
            "seg",
            (
                "csa_core.seg:load_checkpoint",
                "csa_core.seg:read_model_card",
                "csa_core.seg:predict_labels",
                "csa_core.seg:predict_scene",
                "csa_core.seg:evaluate_scene",
                "csa_core.seg:pretrain",
            ),
            "segmentation models (pretrain, evaluate, inference)",
        ),
        Capability(
            "adapt",
            (
                "csa_core.adapt:adapt_one_step",
                "csa_core.adapt:preset",
                "csa_core.adapt:MemoryBank",
                "csa_core.adapt:ReplayBuffer",
                "csa_core.adapt:PretrainReplay",
                "csa_core.adapt:label_entropy",
            ),
            "continual adaptation (joint NeRF + segmentation training with replay)",
        ),
    )
}


def missing_reason(name: str) -> str | None:
    """None when the capability can be used, else a sentence saying what is missing."""
    cap = CAPABILITIES[name]
    absent = []
    for spec in cap.functions:
        module_name, attr = spec.split(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as e:
            return (
                f"{cap.purpose} is not available in this build ({module_name} cannot be imported: "
                f"{e})"
            )
        if not callable(getattr(module, attr, None)):
            absent.append(f"{module_name}.{attr}")
    if absent:
        return f"{cap.purpose} is not available in this build (missing {', '.join(absent)})"
    return None


def available(name: str) -> bool:
    return missing_reason(name) is None


def report() -> dict[str, str | None]:
    """Capability name -> None (available) or why it is not."""
    return {name: missing_reason(name) for name in CAPABILITIES}
