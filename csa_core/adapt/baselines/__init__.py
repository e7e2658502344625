"""Baselines run on the same data and protocol as CSA: Mapping (voxel fusion) and CoTTA.

Names are imported lazily, so the Mapping code and the configs load without torch.
"""

from __future__ import annotations

from csa_core.lazy_exports import lazy_exports

_EXPORTS = {
    "voxel_map": ("PAPER_VOXEL_SIZE", "VoxelMapConfig", "VoxelSemanticMap"),
    "mapping": (
        "MAPPING_FOLDER", "MappingFootprint", "MappingMemory", "build_voxel_map",
        "mapping_memory", "mapping_pseudo_labels", "mapping_replay_buffer", "render_map_labels",
    ),
    "cotta": ("CoTTA", "CoTTAConfig", "CoTTAFootprint", "module_bytes"),
}  # fmt: skip
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
