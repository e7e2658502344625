"""Scene data: types, the scene-folder reader and writer, importers, NYU40 labels, synthetic rooms."""

from csa_core.data.camera import Intrinsics
from csa_core.data.scene import Frame, Scene, SkippedFrame
from csa_core.data.scene_io import read_label_folder, read_scene, write_label_folder, write_scene

__all__ = ["Frame", "Intrinsics", "Scene", "SkippedFrame", "read_label_folder", "read_scene", "write_label_folder", "write_scene"]
