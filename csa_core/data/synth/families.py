"""Room families: the statistics one kind of room is drawn from.

A family fixes room sizes, which furniture appears and how often, what each class looks
like (palette and texture), the lighting and the camera. Geometry per class is shared by
all families (a table is a table everywhere); appearance, layout and light shift between
them, which is the covariate shift continual adaptation has to cope with.
"""

from __future__ import annotations

from dataclasses import dataclass

from csa_core.errors import CSAInputError

RGB = tuple[int, int, int]


@dataclass(frozen=True)
class Look:
    """Appearance of one (class, role): colour choices in sRGB 0..255, texture patterns to
    pick from, the pattern's scale in metres, how far the second colour departs from the
    first (``contrast``) or an explicit ``secondary`` palette, and self-emission (windows,
    screens, lamp shades) as a fraction of the colour."""

    colors: tuple[RGB, ...]
    patterns: tuple[str, ...] = ("noise",)
    scale: float = 0.3
    contrast: float = 0.15
    secondary: tuple[RGB, ...] = ()
    emission: float = 0.0


@dataclass(frozen=True)
class Lighting:
    """Light sources of a family.

    ``placement``: "ceiling" (lights spread under the ceiling) or "window" (a key light in
    front of a window plus an unshadowed ceiling fill). ``intensity`` is the range a light's
    power is drawn from (linear units, shared among ``count`` ceiling lights).
    """

    color: tuple[float, float, float]
    intensity: tuple[float, float]
    count: tuple[int, int]
    ambient: tuple[float, float, float]
    placement: str = "ceiling"
    falloff_m: float = 3.0
    shadow_lights: int = 1  # how many of the lights cast shadows (shadow rays are the main cost)
    fill_color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    fill_intensity: float = 0.0


@dataclass(frozen=True)
class RoomFamily:
    """Everything that differs between families. ``furniture``: (group kind, min, max count)
    placed in that order while there is room; ``looks``: keyed ``"class.role"``, ``"*.role"``
    or ``"class"`` (looked up in that order)."""

    name: str
    description: str
    width_m: tuple[float, float]
    depth_m: tuple[float, float]
    height_m: tuple[float, float]
    furniture: tuple[tuple[str, int, int], ...]
    looks: dict[str, Look]
    lighting: Lighting
    camera_height_m: tuple[float, float] = (1.3, 1.6)
    hfov_deg: float = 65.0
    step_m: float = 0.06  # camera travel per frame: a video subsampled to a few frames per second
    max_turn_deg: float = 6.0  # largest yaw change between consecutive frames
    target_frames: int = 12  # frames spent looking at one piece of furniture
    exposure: float = 1.0
    exposure_jitter: float = 0.0  # std of log exposure across frames (auto-exposure drift)
    sensor_noise: float = 0.0  # std of additive colour noise, in [0, 1] units


_GLASS = Look(((205, 222, 240),), ("noise",), 0.5, 0.05, emission=0.7)
_SCREEN = Look(((18, 20, 26),), ("noise",), 0.5, 0.05, emission=0.05)
_SHADE = Look(((245, 232, 200),), ("fabric",), 0.05, 0.1, emission=0.45)
_COMMON: dict[str, Look] = {
    "*.glass": _GLASS,
    "*.screen": _SCREEN,
    "*.shade": _SHADE,
    "mirror.glass": Look(((190, 200, 208),), ("noise",), 0.4, 0.05, emission=0.35),
}

APARTMENT = RoomFamily(
    name="apartment",
    description="warm, lived-in living rooms and bedrooms: wood, fabrics, pastel walls, warm dim ceiling light",
    width_m=(4.2, 5.6),
    depth_m=(3.6, 5.0),
    height_m=(2.5, 2.7),
    furniture=(
        ("door", 1, 1),
        ("bed", 0, 1),
        ("sofa", 1, 1),
        ("bookshelf", 1, 2),
        ("cabinet", 1, 1),
        ("dresser", 0, 1),
        ("window_curtains", 1, 2),
        ("dining", 0, 1),
        ("floor_lamp", 0, 1),
        ("picture", 1, 3),
        ("mirror", 0, 1),
    ),
    looks={
        **_COMMON,
        "wall": Look(((236, 226, 206), (212, 220, 196), (242, 216, 196), (226, 214, 226)), ("noise", "stripes"), 0.12, 0.06),
        "floor": Look(((168, 122, 80), (142, 98, 62), (186, 146, 100)), ("planks",), 0.14, 0.3),
        "ceiling": Look(((246, 241, 232),), ("noise",), 0.5, 0.03),
        "*.frame": Look(((122, 86, 56), (96, 66, 44)), ("wood",), 0.02, 0.25),
        "table.top": Look(((152, 102, 62), (124, 82, 52), (170, 122, 78)), ("wood",), 0.025, 0.3),
        "chair": Look(((140, 92, 56), (110, 74, 48)), ("wood",), 0.02, 0.25),
        "bed.soft": Look(((232, 226, 214), (204, 214, 232), (236, 220, 206)), ("fabric",), 0.04, 0.08),
        "pillow": Look(((224, 204, 182), (184, 64, 62), (92, 122, 164), (214, 180, 90)), ("fabric",), 0.03, 0.1),
        "sofa": Look(((122, 92, 72), (92, 112, 82), (152, 64, 54), (170, 150, 120)), ("fabric",), 0.03, 0.12),
        "bookshelf": Look(((112, 76, 46), (150, 104, 64)), ("wood",), 0.02, 0.25),
        "books": Look(((160, 52, 42), (44, 84, 124), (200, 170, 90)), ("spines",), 0.035, 0.4, secondary=((60, 110, 70), (220, 210, 190))),
        "cabinet": Look(((162, 116, 72), (222, 216, 204)), ("wood",), 0.025, 0.2),
        "dresser": Look(((150, 104, 62), (176, 130, 84)), ("wood",), 0.025, 0.25),
        "night stand": Look(((150, 104, 62), (120, 82, 50)), ("wood",), 0.025, 0.25),
        "door": Look(((152, 106, 66), (232, 228, 218)), ("wood",), 0.03, 0.2),
        "door.frame": Look(((236, 232, 222),), ("noise",), 0.3, 0.05),
        "window.frame": Look(((238, 236, 230),), ("noise",), 0.3, 0.04),
        "curtain": Look(((196, 154, 112), (134, 44, 54), (222, 212, 190), (120, 140, 110)), ("fabric", "stripes"), 0.08, 0.15),
        "picture.canvas": Look(((200, 90, 60), (70, 110, 150), (220, 180, 80)), ("painting",), 0.15, 0.6, secondary=((40, 60, 40), (230, 220, 200), (120, 40, 60))),
        "picture.frame": Look(((170, 140, 70), (90, 60, 40)), ("wood",), 0.01, 0.2),
        "floor mat": Look(((152, 52, 52), (182, 142, 92), (90, 100, 140)), ("tiles", "stripes"), 0.12, 0.35),
        "lamp.frame": Look(((172, 142, 82),), ("noise",), 0.1, 0.1),
        "box": Look(((176, 136, 96), (200, 190, 170)), ("noise",), 0.08, 0.15),
        "television.frame": Look(((34, 34, 36),), ("noise",), 0.2, 0.05),
        "mirror.frame": Look(((170, 140, 70),), ("wood",), 0.01, 0.2),
    },
    lighting=Lighting(color=(1.0, 0.8, 0.58), intensity=(0.9, 1.2), count=(1, 2), ambient=(0.2, 0.17, 0.13)),
    camera_height_m=(1.45, 1.65),
    hfov_deg=62.0,
    step_m=0.055,
    exposure=1.0,
    exposure_jitter=0.08,
    sensor_noise=0.006,
)

OFFICE = RoomFamily(
    name="office",
    description="bright open offices: desks and chairs in rows, grey carpet tiles, white walls, cool even light",
    width_m=(5.5, 7.5),
    depth_m=(4.5, 6.0),
    height_m=(2.7, 3.0),
    furniture=(
        ("door", 1, 1),
        ("desk", 2, 4),
        ("bookshelf", 1, 2),
        ("tall_cabinet", 1, 2),
        ("window_blinds", 1, 3),
        ("shelving", 0, 1),
        ("dining", 0, 1),
        ("cabinet", 0, 1),
        ("boxes", 1, 2),
        ("whiteboard", 1, 1),
        ("picture", 0, 2),
        ("wall_tv", 0, 1),
    ),
    looks={
        **_COMMON,
        "wall": Look(((226, 229, 231), (202, 207, 212), (186, 202, 216)), ("noise",), 0.4, 0.04),
        "floor": Look(((92, 97, 108), (72, 82, 96), (110, 110, 104)), ("tiles",), 0.5, 0.18),
        "ceiling": Look(((236, 236, 234),), ("tiles",), 0.6, 0.06),
        "*.frame": Look(((132, 136, 142), (60, 62, 66)), ("noise",), 0.1, 0.08),
        "desk.top": Look(((232, 232, 226), (204, 204, 202), (216, 192, 152)), ("noise",), 0.2, 0.06),
        "desk": Look(((140, 145, 150), (200, 200, 198)), ("noise",), 0.2, 0.06),
        "table.top": Look(((232, 232, 226), (196, 198, 200)), ("noise",), 0.2, 0.06),
        "chair": Look(((36, 36, 42), (32, 46, 82), (64, 64, 70)), ("fabric",), 0.015, 0.15),
        "chair.frame": Look(((58, 58, 62), (160, 162, 166)), ("noise",), 0.1, 0.08),
        "bookshelf": Look(((200, 200, 200), (150, 152, 156)), ("noise",), 0.2, 0.05),
        "books": Look(((40, 70, 140), (230, 230, 226), (180, 40, 40)), ("spines",), 0.03, 0.3, secondary=((40, 40, 44), (200, 180, 60))),
        "cabinet": Look(((162, 166, 172), (206, 208, 210)), ("noise",), 0.2, 0.05),
        "shelves": Look(((140, 142, 146),), ("noise",), 0.1, 0.08),
        "box": Look(((172, 132, 92), (184, 150, 110)), ("noise",), 0.08, 0.15),
        "whiteboard": Look(((246, 246, 246),), ("noise",), 0.5, 0.02, emission=0.05),
        "blinds": Look(((222, 222, 216), (190, 196, 204)), ("hstripes",), 0.025, 0.25),
        "door": Look(((162, 167, 177), (122, 92, 62)), ("noise",), 0.2, 0.05),
        "door.frame": Look(((150, 154, 160),), ("noise",), 0.2, 0.05),
        "window.frame": Look(((160, 164, 170),), ("noise",), 0.2, 0.04),
        "picture.canvas": Look(((40, 100, 170), (230, 230, 230), (60, 160, 120)), ("painting", "stripes"), 0.2, 0.6, secondary=((30, 40, 60), (200, 210, 220))),
        "picture.frame": Look(((40, 40, 42), (190, 190, 190)), ("noise",), 0.2, 0.05),
        "lamp.frame": Look(((40, 40, 44),), ("noise",), 0.1, 0.05),
        "television.frame": Look(((30, 30, 32),), ("noise",), 0.2, 0.05),
    },
    lighting=Lighting(color=(0.88, 0.95, 1.0), intensity=(0.75, 0.95), count=(2, 4), ambient=(0.3, 0.32, 0.35)),
    camera_height_m=(1.2, 1.4),
    hfov_deg=66.0,
    step_m=0.065,
    exposure=1.0,
    exposure_jitter=0.04,
    sensor_noise=0.004,
)

STUDIO = RoomFamily(
    name="studio",
    description="large industrial lofts: brick or concrete, dark ceilings, saturated furniture, side light from a window",
    width_m=(6.0, 8.0),
    depth_m=(5.0, 6.5),
    height_m=(3.0, 3.4),
    furniture=(
        ("door", 1, 1),
        ("kitchen", 1, 1),
        ("sofa", 1, 1),
        ("shelving", 1, 2),
        ("window", 1, 3),
        ("bed", 0, 1),
        ("dining", 1, 1),
        ("boxes", 1, 3),
        ("floor_lamp", 0, 1),
        ("cabinet", 0, 1),
        ("picture", 1, 3),
    ),
    looks={
        **_COMMON,
        "wall": Look(((152, 72, 52), (172, 172, 166), (124, 58, 44), (96, 98, 104)), ("brick", "noise"), 0.4, 0.3),
        "floor": Look(((132, 132, 126), (104, 102, 96), (70, 52, 40)), ("noise",), 0.6, 0.35),
        "ceiling": Look(((72, 72, 78), (110, 110, 112)), ("noise",), 0.8, 0.2),
        "*.frame": Look(((34, 34, 36), (70, 72, 76)), ("noise",), 0.1, 0.1),
        "table.top": Look(((82, 56, 36), (236, 236, 232), (40, 40, 40)), ("wood", "noise"), 0.03, 0.35),
        "chair": Look(((222, 62, 52), (240, 200, 52), (62, 142, 202), (30, 30, 30)), ("noise",), 0.2, 0.06),
        "sofa": Look(((202, 122, 32), (32, 122, 132), (182, 42, 42), (90, 60, 110)), ("fabric",), 0.02, 0.2),
        "pillow": Look(((240, 230, 60), (230, 90, 140), (40, 40, 40), (250, 250, 250)), ("fabric", "stripes"), 0.05, 0.3),
        "bed.soft": Look(((150, 150, 156), (60, 70, 90)), ("fabric",), 0.03, 0.15),
        "counter": Look(((204, 204, 198), (40, 40, 42), (150, 120, 90)), ("noise",), 0.15, 0.3),
        "cabinet": Look(((42, 82, 62), (42, 52, 82), (30, 30, 32), (190, 70, 40)), ("noise",), 0.3, 0.08),
        "refrigerator": Look(((192, 192, 198), (200, 222, 212), (180, 40, 40)), ("noise",), 0.3, 0.06),
        "shelves": Look(((40, 40, 42), (150, 100, 60)), ("noise", "wood"), 0.05, 0.15),
        "box": Look(((160, 120, 80), (52, 92, 162), (60, 130, 70)), ("noise",), 0.1, 0.2),
        "night stand": Look(((30, 30, 32), (180, 60, 40)), ("noise",), 0.2, 0.1),
        "door": Look(((92, 97, 102), (40, 40, 42)), ("noise",), 0.2, 0.12),
        "door.frame": Look(((36, 36, 38),), ("noise",), 0.2, 0.05),
        "window.frame": Look(((30, 30, 32),), ("noise",), 0.2, 0.05),
        "window.glass": Look(((220, 232, 244),), ("noise",), 0.5, 0.05, emission=0.9),
        "picture.canvas": Look(((230, 40, 40), (30, 30, 30), (250, 200, 0), (0, 90, 180)), ("painting", "tiles"), 0.2, 0.8, secondary=((250, 250, 250), (20, 20, 20))),
        "picture.frame": Look(((20, 20, 20), (240, 240, 240)), ("noise",), 0.2, 0.05),
        "floor mat": Look(((200, 60, 40), (40, 40, 40), (220, 200, 150)), ("tiles", "noise"), 0.2, 0.5),
        "lamp.frame": Look(((24, 24, 24),), ("noise",), 0.1, 0.05),
        "television.frame": Look(((24, 24, 26),), ("noise",), 0.2, 0.05),
    },
    lighting=Lighting(
        color=(1.0, 0.97, 0.9),
        intensity=(2.2, 2.8),
        count=(1, 1),
        ambient=(0.1, 0.1, 0.12),
        placement="window",
        falloff_m=2.5,
        fill_color=(0.75, 0.82, 1.0),
        fill_intensity=0.35,
    ),
    camera_height_m=(0.9, 1.2),
    hfov_deg=69.0,
    step_m=0.075,
    exposure=1.25,
    exposure_jitter=0.15,
    sensor_noise=0.012,
)

FAMILIES: dict[str, RoomFamily] = {f.name: f for f in (APARTMENT, OFFICE, STUDIO)}


def family_names() -> list[str]:
    """Names of the known families, in a stable order."""
    return list(FAMILIES)


def get_family(family: str | RoomFamily) -> RoomFamily:
    """A family by name (or pass one through); unknown names are a user error."""
    if isinstance(family, RoomFamily):
        return family
    if family not in FAMILIES:
        raise CSAInputError("--family", f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
    return FAMILIES[family]
