"""Room families: the statistics one kind of room is drawn from.

All families share one catalogue of furniture and one appearance distribution per class
(``BASE_LOOKS``): a sofa is built and coloured from the same ranges everywhere. A family
shifts that shared distribution (hue, saturation, brightness, tint, texture mixture), uses
its own room sizes, furniture counts, lighting and camera, and adds a few rarer pieces of
its own. Each room then draws its own colours around the family's shift, so no class has
one fixed colour. The result is a moderate covariate shift between families, like the shift
between real scenes that continual adaptation has to cope with.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from csa_core.errors import CSAInputError

RGB = tuple[int, int, int]


@dataclass(frozen=True)
class Look:
    """Appearance distribution of one (class, role).

    ``colors``: base colours in sRGB 0..255, one is picked per instance; ``patterns`` with
    optional ``pattern_weights`` and per-pattern ``scales`` (metres; ``scale`` when empty);
    ``contrast``: how far the second colour departs from the first, or an explicit
    ``secondary`` palette; ``emission``: self-emission (windows, screens, shades) as a
    fraction of the colour. Each instance jitters hue (degrees), log saturation and log
    brightness with the ``*_jitter`` standard deviations.
    """

    colors: tuple[RGB, ...]
    patterns: tuple[str, ...] = ("noise",)
    scale: float = 0.3
    contrast: float = 0.15
    secondary: tuple[RGB, ...] = ()
    emission: float = 0.0
    pattern_weights: tuple[float, ...] = ()
    scales: tuple[float, ...] = ()
    hue_jitter: float = 6.0
    saturation_jitter: float = 0.12
    value_jitter: float = 0.08


@dataclass(frozen=True)
class Appearance:
    """A family's shift of the shared looks and the spread of one room around it.

    Colours are rotated by ``hue_deg``, their saturation and brightness (HSV value) scaled by
    ``saturation`` and ``value``, then multiplied by ``tint`` (RGB). ``shell_tint`` further
    tints walls, floor and ceiling (paint and material choices). Each room draws its own
    offset: hue (std ``room_hue_deg``), log saturation and log brightness (stds
    ``room_saturation``, ``room_value``). ``pattern_bias`` multiplies the weight of named
    texture patterns wherever a look offers them.
    """

    hue_deg: float = 0.0
    saturation: float = 1.0
    value: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    shell_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    room_hue_deg: float = 15.0
    room_saturation: float = 0.15
    room_value: float = 0.08
    pattern_bias: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class Lighting:
    """Light sources of a family.

    ``placement``: "ceiling" (lights spread under the ceiling) or "window" (a key light in
    front of a window plus an unshadowed ceiling fill). ``intensity`` is the range a light's
    power is drawn from (linear units, shared among ``count`` ceiling lights).
    ``color_jitter`` is the std of a room's log colour change per channel (bulbs differ).
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
    color_jitter: float = 0.0


@dataclass(frozen=True)
class RoomFamily:
    """Everything that differs between families. ``furniture``: (group kind, min, max count)
    placed in that order while there is room; ``looks``: keyed ``"class.role"``, ``"*.role"``
    or ``"class"`` (looked up in that order); ``appearance``: the family's shift of them."""

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
    appearance: Appearance = field(default_factory=Appearance)


_WOOD = ((152, 104, 64), (124, 84, 52), (176, 130, 84), (104, 72, 46))
_METAL = ((140, 144, 150), (62, 64, 68), (36, 36, 38), (196, 198, 200))
_PAINTED = ((232, 230, 222), (206, 208, 210), (44, 46, 50), (64, 96, 80), (60, 72, 104))
_FABRIC = (
    (122, 92, 72),
    (92, 112, 82),
    (152, 64, 54),
    (170, 150, 120),
    (76, 80, 88),
    (150, 150, 156),
    (48, 92, 128),
    (178, 120, 52),
)
_WOOD_NOISE = ("wood", "noise")

# One appearance distribution per (class, role), shared by all families.
BASE_LOOKS: dict[str, Look] = {
    "*.glass": Look(((205, 222, 240),), ("noise",), 0.5, 0.05, emission=0.7, hue_jitter=3.0),
    "*.screen": Look(((18, 20, 26),), ("noise",), 0.5, 0.05, emission=0.05),
    "*.shade": Look(((245, 232, 200), (236, 236, 232)), ("fabric",), 0.05, 0.1, emission=0.45),
    "*.frame": Look(_WOOD + _METAL, _WOOD_NOISE, 0.03, 0.2, scales=(0.02, 0.1)),
    "wall": Look(
        (
            (236, 232, 224),
            (228, 228, 226),
            (232, 226, 214),
            (218, 222, 226),
            (240, 240, 236),
            (226, 222, 214),
            (218, 224, 216),
        ),
        ("noise", "stripes", "brick"),
        0.3,
        0.06,
        pattern_weights=(0.7, 0.15, 0.15),
        scales=(0.4, 0.12, 0.26),
        hue_jitter=8.0,
        saturation_jitter=0.3,
        value_jitter=0.06,
    ),
    "floor": Look(
        (
            (168, 122, 80),
            (142, 98, 62),
            (186, 146, 100),
            (120, 116, 110),
            (96, 100, 108),
            (150, 146, 138),
            (110, 84, 64),
        ),
        ("planks", "tiles", "noise"),
        0.3,
        0.25,
        scales=(0.14, 0.5, 0.6),
        value_jitter=0.12,
    ),
    "ceiling": Look(
        ((246, 241, 232), (236, 236, 234), (228, 228, 226)),
        ("noise", "tiles"),
        0.5,
        0.04,
        pattern_weights=(0.8, 0.2),
        scales=(0.5, 0.6),
    ),
    "table.top": Look(
        _WOOD + ((232, 232, 226), (196, 198, 200), (58, 56, 54)),
        _WOOD_NOISE,
        0.03,
        0.3,
        scales=(0.025, 0.2),
    ),
    "desk.top": Look(
        _WOOD + ((232, 232, 226), (204, 204, 202), (58, 56, 54)),
        _WOOD_NOISE,
        0.03,
        0.25,
        scales=(0.025, 0.2),
    ),
    "desk": Look(
        _WOOD + ((200, 200, 198), (140, 145, 150)), _WOOD_NOISE, 0.03, 0.2, scales=(0.025, 0.2)
    ),
    "chair": Look(
        _WOOD[:2]
        + ((40, 40, 46), (34, 48, 84), (66, 66, 72), (200, 70, 56), (62, 132, 186), (226, 190, 60)),
        ("wood", "fabric", "noise"),
        0.03,
        0.15,
        scales=(0.02, 0.015, 0.2),
    ),
    "bed.soft": Look(
        ((232, 226, 214), (204, 214, 232), (236, 220, 206), (150, 150, 156), (70, 80, 100)),
        ("fabric",),
        0.04,
        0.1,
    ),
    "pillow": Look(
        (
            (224, 204, 182),
            (184, 64, 62),
            (92, 122, 164),
            (214, 180, 90),
            (236, 236, 230),
            (50, 50, 52),
        ),
        ("fabric", "stripes"),
        0.04,
        0.15,
        pattern_weights=(0.8, 0.2),
    ),
    "sofa": Look(_FABRIC, ("fabric",), 0.03, 0.15),
    "bookshelf": Look(
        _WOOD + ((220, 218, 210), (150, 152, 156), (40, 40, 42)),
        _WOOD_NOISE,
        0.03,
        0.2,
        scales=(0.02, 0.2),
    ),
    "books": Look(
        ((160, 52, 42), (44, 84, 124), (200, 170, 90), (40, 70, 140), (230, 230, 226)),
        ("spines",),
        0.035,
        0.4,
        secondary=((60, 110, 70), (220, 210, 190), (40, 40, 44)),
    ),
    "cabinet": Look(
        _WOOD + _PAINTED,
        _WOOD_NOISE,
        0.03,
        0.15,
        pattern_weights=(0.45, 0.55),
        scales=(0.025, 0.25),
    ),
    "dresser": Look(_WOOD + _PAINTED[:2], _WOOD_NOISE, 0.03, 0.2, scales=(0.025, 0.25)),
    "night stand": Look(_WOOD + _PAINTED[:3], _WOOD_NOISE, 0.03, 0.2, scales=(0.025, 0.25)),
    "shelves": Look(_METAL + _WOOD[:2], ("noise", "wood"), 0.1, 0.1, scales=(0.1, 0.05)),
    "box": Look(
        ((176, 136, 96), (200, 190, 170), (160, 120, 80), (52, 92, 162), (60, 130, 70)),
        ("noise",),
        0.08,
        0.15,
    ),
    "door": Look(
        _WOOD[:2] + ((232, 228, 218), (162, 167, 177), (92, 97, 102)),
        _WOOD_NOISE,
        0.03,
        0.15,
        scales=(0.03, 0.2),
    ),
    "door.frame": Look(
        ((236, 232, 222), (150, 154, 160), (120, 84, 54), (48, 48, 50)), ("noise",), 0.3, 0.05
    ),
    "window.frame": Look(((238, 236, 230), (160, 164, 170), (40, 40, 42)), ("noise",), 0.3, 0.04),
    "curtain": Look(
        (
            (196, 154, 112),
            (134, 44, 54),
            (222, 212, 190),
            (120, 140, 110),
            (80, 90, 120),
            (180, 180, 176),
        ),
        ("fabric", "stripes"),
        0.08,
        0.15,
        pattern_weights=(0.75, 0.25),
    ),
    "blinds": Look(((222, 222, 216), (190, 196, 204), (170, 150, 120)), ("hstripes",), 0.025, 0.25),
    "picture.canvas": Look(
        (
            (200, 90, 60),
            (70, 110, 150),
            (220, 180, 80),
            (60, 160, 120),
            (230, 230, 230),
            (30, 30, 30),
        ),
        ("painting", "stripes", "tiles"),
        0.15,
        0.6,
        secondary=((40, 60, 40), (230, 220, 200), (120, 40, 60), (30, 40, 60), (250, 250, 250)),
        pattern_weights=(0.7, 0.15, 0.15),
        scales=(0.15, 0.2, 0.2),
        hue_jitter=30.0,
    ),
    "picture.frame": Look(
        ((170, 140, 70), (90, 60, 40), (40, 40, 42), (220, 220, 218)),
        _WOOD_NOISE,
        0.02,
        0.15,
        scales=(0.01, 0.2),
    ),
    "floor mat": Look(
        ((152, 52, 52), (182, 142, 92), (90, 100, 140), (60, 60, 62), (200, 190, 160)),
        ("tiles", "stripes", "noise"),
        0.15,
        0.4,
        hue_jitter=15.0,
    ),
    "lamp.frame": Look(((172, 142, 82), (40, 40, 44), (200, 200, 204)), ("noise",), 0.1, 0.1),
    "television.frame": Look(((34, 34, 36), (60, 60, 64)), ("noise",), 0.2, 0.05),
    "mirror.frame": Look(
        ((170, 140, 70), (40, 40, 42), (220, 220, 218)),
        ("wood", "noise"),
        0.02,
        0.2,
        scales=(0.01, 0.2),
    ),
    "mirror.glass": Look(((176, 186, 196),), ("noise",), 0.15, 0.3, emission=0.25, hue_jitter=3.0),
    "whiteboard": Look(
        ((246, 246, 246),), ("noise",), 0.5, 0.02, emission=0.05, saturation_jitter=0.0
    ),
    "otherprop": Look(
        ((176, 92, 62), (226, 220, 208), (60, 62, 66), (150, 156, 160)), ("noise",), 0.1, 0.1
    ),
    "otherprop.stem": Look(((82, 96, 48), (104, 80, 52)), ("noise",), 0.05, 0.15),
    "otherprop.leaf": Look(
        ((58, 112, 48), (40, 90, 44), (92, 134, 58), (70, 100, 40)),
        ("noise",),
        0.04,
        0.2,
        hue_jitter=10.0,
    ),
    "counter": Look(
        ((204, 204, 198), (40, 40, 42), (150, 120, 90), (120, 120, 116)),
        ("noise", "wood"),
        0.15,
        0.3,
        scales=(0.15, 0.03),
    ),
    "refrigerator": Look(((196, 196, 200), (220, 220, 218), (60, 60, 64)), ("noise",), 0.3, 0.05),
}


APARTMENT = RoomFamily(
    name="apartment",
    description=(
        "lived-in living rooms and bedrooms: warm tints, wooden floors, curtains, warm dim ceiling "
        "light"
    ),
    width_m=(4.2, 5.8),
    depth_m=(3.6, 5.2),
    height_m=(2.45, 2.75),
    furniture=(
        ("door", 1, 1),
        ("sofa", 1, 1),
        ("dining", 1, 1),
        ("bed", 0, 1),
        ("bookshelf", 1, 1),
        ("cabinet", 1, 1),
        ("window_curtains", 1, 2),
        ("window_blinds", 0, 1),
        ("desk", 0, 1),
        ("boxes", 1, 1),
        ("floor_lamp", 0, 1),
        ("ladder_shelf", 0, 1),
        ("chairs", 0, 1),
        ("plant", 1, 2),
        ("picture", 1, 3),
        ("dresser", 0, 1),
        ("mirror", 0, 1),
        ("arc_lamp", 0, 1),
    ),
    looks=dict(BASE_LOOKS),
    lighting=Lighting(
        color=(1.0, 0.93, 0.85),
        intensity=(0.85, 1.3),
        count=(1, 2),
        ambient=(0.2, 0.19, 0.17),
        color_jitter=0.1,
    ),
    camera_height_m=(1.4, 1.65),
    hfov_deg=62.0,
    step_m=0.055,
    exposure=1.0,
    exposure_jitter=0.08,
    sensor_noise=0.006,
    appearance=Appearance(
        hue_deg=4.0,
        saturation=1.05,
        value=0.97,
        tint=(1.01, 1.0, 0.98),
        shell_tint=(1.01, 1.0, 0.98),
        pattern_bias=(
            ("planks", 4.0),
            ("wood", 2.0),
            ("stripes", 1.5),
            ("brick", 0.3),
            ("fabric", 1.5),
        ),
    ),
)

OFFICE = RoomFamily(
    name="office",
    description=(
        "bright offices: desks in rows, carpet tiles, cool white walls and paint, cool even light"
    ),
    width_m=(5.2, 7.2),
    depth_m=(4.4, 6.0),
    height_m=(2.6, 3.0),
    furniture=(
        ("door", 1, 1),
        ("meeting", 0, 1),
        ("sofa", 0, 1),
        ("office_desk", 2, 4),
        ("window_blinds", 1, 2),
        ("window_curtains", 0, 1),
        ("bookshelf", 1, 1),
        ("cabinet", 1, 1),
        ("dining", 0, 1),
        ("tall_cabinet", 0, 1),
        ("chairs", 1, 2),
        ("plant", 1, 2),
        ("boxes", 1, 1),
        ("floor_lamp", 0, 1),
        ("picture", 1, 2),
        ("whiteboard", 0, 1),
        ("shelving", 0, 1),
        ("wall_tv", 0, 1),
    ),
    looks=dict(BASE_LOOKS),
    lighting=Lighting(
        color=(0.96, 0.98, 1.0),
        intensity=(0.75, 1.0),
        count=(2, 4),
        ambient=(0.22, 0.23, 0.24),
        color_jitter=0.1,
    ),
    camera_height_m=(1.25, 1.5),
    hfov_deg=66.0,
    step_m=0.065,
    exposure=1.0,
    exposure_jitter=0.04,
    sensor_noise=0.004,
    appearance=Appearance(
        hue_deg=-6.0,
        saturation=0.9,
        value=1.0,
        tint=(0.98, 1.0, 1.02),
        shell_tint=(0.97, 0.99, 1.03),
        pattern_bias=(
            ("tiles", 4.0),
            ("noise", 2.0),
            ("wood", 0.6),
            ("stripes", 0.4),
            ("brick", 0.2),
        ),
    ),
)

STUDIO = RoomFamily(
    name="studio",
    description=(
        "large lofts: painted brick, concrete floors, saturated furniture, side light from a window"
    ),
    width_m=(5.2, 7.2),
    depth_m=(4.4, 6.0),
    height_m=(2.8, 3.2),
    furniture=(
        ("door", 1, 1),
        ("sofa", 1, 1),
        ("window_curtains", 1, 1),
        ("window", 0, 2),
        ("dining", 1, 1),
        ("cabinet", 1, 1),
        ("bed", 0, 1),
        ("desk", 0, 1),
        ("bookshelf", 0, 1),
        ("shelving", 1, 1),
        ("boxes", 1, 2),
        ("floor_lamp", 0, 1),
        ("stools", 1, 1),
        ("plant", 1, 3),
        ("arc_lamp", 0, 1),
        ("ladder_shelf", 0, 1),
        ("chairs", 0, 1),
        ("picture", 1, 3),
        ("kitchen", 0, 1),
    ),
    looks=dict(BASE_LOOKS),
    lighting=Lighting(
        color=(1.0, 0.96, 0.9),
        intensity=(1.3, 1.8),
        count=(1, 1),
        ambient=(0.2, 0.2, 0.21),
        placement="window",
        falloff_m=2.8,
        fill_color=(0.8, 0.86, 1.0),
        fill_intensity=0.7,
        color_jitter=0.1,
    ),
    camera_height_m=(1.25, 1.5),
    hfov_deg=68.0,
    step_m=0.07,
    exposure=1.2,
    exposure_jitter=0.12,
    sensor_noise=0.01,
    appearance=Appearance(
        hue_deg=0.0,
        saturation=1.05,
        value=0.9,
        tint=(1.0, 0.99, 0.98),
        shell_tint=(0.96, 0.96, 0.97),
        pattern_bias=(("brick", 5.0), ("noise", 2.0), ("tiles", 0.5), ("planks", 0.5)),
    ),
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
