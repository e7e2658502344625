"""Baselines run on the same data and protocol as CSA: Mapping (voxel fusion) and CoTTA.

Names are imported lazily, so the Mapping code and the configs load without torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "voxel_map": ("PAPER_VOXEL_SIZE", "VoxelMapConfig", "VoxelSemanticMap"),
    "mapping": (
        "MAPPING_FOLDER", "MappingFootprint", "MappingMemory", "MappingStep", "build_voxel_map",
        "finetune_on_map_labels", "mapping_adapt", "mapping_memory", "mapping_pseudo_labels",
        "mapping_replay_buffer", "render_map_labels",
    ),
    "cotta": ("CoTTA", "CoTTAConfig", "CoTTAFootprint", "cotta_adapt", "module_bytes"),
}  # fmt: skip
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'csa_core.adapt.baselines' has no attribute {name!r}")
    return getattr(importlib.import_module(f"csa_core.adapt.baselines.{module}"), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
