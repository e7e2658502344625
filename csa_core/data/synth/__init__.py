"""Procedural synthetic rooms: the project's embedded default data.

Rooms are a box (walls, floor, ceiling) holding furniture built from oriented boxes and
round rods (capsules), thin, tilted and curved parts included, with procedural textures and
Lambertian lighting, seen by a camera walking through them or from viewpoints spread at
random (the capture mode); every frame has colour, z-depth, a camera-to-world pose and exact
NYU40 labels. Families of rooms differ in layout, appearance and light, to create domain
shift between scenes.
"""

from csa_core.data.synth.families import (
    FAMILIES,
    Lighting,
    Look,
    RoomFamily,
    family_names,
    get_family,
)
from csa_core.data.synth.generate import (
    generate_scene,
    intrinsics_for,
    parse_size,
    scene_seed,
    synthesize,
)
from csa_core.data.synth.kinect import (
    NOISY_FOLDER,
    KinectConfig,
    axial_sigma,
    degrade_scene,
    degrade_scene_folder,
    mix_depth_edges,
)

__all__ = [
    "FAMILIES",
    "KinectConfig",
    "Lighting",
    "Look",
    "NOISY_FOLDER",
    "RoomFamily",
    "axial_sigma",
    "degrade_scene",
    "degrade_scene_folder",
    "family_names",
    "generate_scene",
    "get_family",
    "intrinsics_for",
    "mix_depth_edges",
    "parse_size",
    "scene_seed",
    "synthesize",
]
