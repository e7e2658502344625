"""Scene data: types, the scene-folder reader and writer, importers, NYU40 labels, synthetic rooms.

Names are imported lazily, so light modules (``csa_core.data.nyu40``, ``csa_core.data.camera``)
load without OpenCV.
"""

from __future__ import annotations

from csa_core.lazy_exports import lazy_exports

_EXPORTS = {
    "camera": ("Intrinsics",),
    "scene": ("Frame", "Scene", "SkippedFrame"),
    "scene_io": ("read_label_folder", "read_scene", "write_label_folder", "write_scene"),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
