"""Hash-grid Semantic-NeRF: fuse per-frame labels in 3D, render labels, images and depth, and
store each scene compactly for the memory bank (DESIGN.md "The method", steps 2, 3 and 5).

Typical use::

    nerf, stats = fit_semantic_nerf(scene, "predictions", "fast")
    labels = render_pseudo_labels(nerf, scene, views="train")
    save_checkpoint(nerf, "scene.safetensors")
"""

from csa_core.device import resolve_device
from csa_core.nerf.checkpoint import checkpoint_info, load_checkpoint, save_checkpoint
from csa_core.nerf.config import NerfConfig, preset
from csa_core.nerf.fit import FitStats, fit_semantic_nerf
from csa_core.nerf.label_noise import LabelNoiseConfig, corrupt_labels
from csa_core.nerf.model import SemanticNerf
from csa_core.nerf.render import (
    RenderedView,
    interpolate_pose,
    novel_view_poses,
    render_image,
    render_pseudo_labels,
    render_views,
    write_rendered_views,
)

__all__ = [
    "FitStats",
    "LabelNoiseConfig",
    "NerfConfig",
    "RenderedView",
    "SemanticNerf",
    "checkpoint_info",
    "corrupt_labels",
    "fit_semantic_nerf",
    "interpolate_pose",
    "load_checkpoint",
    "novel_view_poses",
    "preset",
    "render_image",
    "render_pseudo_labels",
    "render_views",
    "resolve_device",
    "save_checkpoint",
    "write_rendered_views",
]
