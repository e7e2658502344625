"""Hash-grid Semantic-NeRF: fuse per-frame labels in 3D, render labels, images and depth, and
store each scene compactly for the memory bank
(docs/method.md "Fuse in 3D", "Render pseudo-labels", "Remember").

Typical use::

    nerf, stats = fit_semantic_nerf(scene, "predictions", "fast")
    labels = render_pseudo_labels(nerf, scene, views="train")
    save_checkpoint(nerf, "scene.safetensors")

Names are imported lazily, so ``csa_core.nerf.config`` (and the command line that reads its
presets) loads without torch.
"""

from __future__ import annotations

from csa_core.lazy_exports import lazy_exports

_EXPORTS = {
    "checkpoint": ("checkpoint_info", "load_checkpoint", "save_checkpoint"),
    "config": ("NerfConfig", "build_config", "preset"),
    "fit": ("FitStats", "fit_semantic_nerf"),
    "model": ("SemanticNerf",),
    "rays": ("RayBank", "camera_directions", "image_rays"),
    "render": (
        "RenderedView", "interpolate_pose", "novel_view_poses", "render_frames", "render_image",
        "render_pseudo_labels", "render_views", "write_rendered_views",
    ),
    "trainer": ("NerfTrainer",),
}  # fmt: skip
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
