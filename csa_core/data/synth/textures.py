"""Materials and procedural textures evaluated at surface points.

A texture is a function of the hit point in the local frame of the surface it lies on
(box frame for furniture, world frame for walls, floor and ceiling), never of the view, so
every camera sees the same albedo at the same point. On each face two tangent coordinates
(u, v) are used: on vertical faces u runs horizontally and v = z; on horizontal faces
(u, v) = (x, y).
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np

from csa_core.data.synth.families import Appearance, Look, RoomFamily
from csa_core.data.synth.noise import fbm3, hash01

PATTERNS = (
    "noise",
    "wood",
    "planks",
    "tiles",
    "stripes",
    "hstripes",
    "brick",
    "spines",
    "fabric",
    "painting",
)
_DEFAULT_LOOK = Look(((150, 150, 150),))
_MORTAR = np.array([0.42, 0.40, 0.37])


def find_look(family: RoomFamily, label: str, role: str) -> Look:
    """The family's look for a part: ``label.role``, then ``*.role``, then ``label``."""
    for key in (f"{label}.{role}", f"*.{role}", label):
        if key in family.looks:
            return family.looks[key]
    return _DEFAULT_LOOK


def has_look(family: RoomFamily, label: str, role: str) -> bool:
    return find_look(family, label, role) is not _DEFAULT_LOOK


SHELL_CLASSES = ("wall", "floor", "ceiling")


def shift_color(
    rgb: tuple[int, int, int], hue_deg: float, sat: float, val: float, tint: np.ndarray
) -> np.ndarray:
    """An sRGB 0..255 colour rotated in hue, scaled in saturation and value, then tinted;
    returned as linear reflectance."""
    h, s, v = colorsys.rgb_to_hsv(*(c / 255.0 for c in rgb))
    h = (h + hue_deg / 360.0) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, min(s * sat, 1.0), min(v * val, 1.0))
    return np.clip(np.array([r, g, b]) * tint, 0.0, 1.0) ** 2.2


@dataclass
class MaterialTable:
    """Per-material arrays; a material is one instance of a look with its drawn colours.

    ``appearance`` is the family's shift and ``room`` the room's own offset (hue degrees,
    log saturation, log value), drawn once per room by :meth:`for_room`.
    """

    pattern: list[int]
    color1: list[np.ndarray]
    color2: list[np.ndarray]
    scale: list[float]
    emission: list[float]
    offset: list[np.ndarray]
    appearance: Appearance = field(default_factory=Appearance)
    room: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def empty(cls) -> MaterialTable:
        """A table with no shift (the looks' own colour distributions)."""
        return cls([], [], [], [], [], [])

    @classmethod
    def for_room(cls, appearance: Appearance, rng: np.random.Generator) -> MaterialTable:
        """A table for one room of a family: the family's shift plus the room's own offset."""
        room = (
            float(rng.normal(0.0, appearance.room_hue_deg)),
            float(rng.normal(0.0, appearance.room_saturation)),
            float(rng.normal(0.0, appearance.room_value)),
        )
        return cls([], [], [], [], [], [], appearance, room)

    def _pick_pattern(self, look: Look, rng: np.random.Generator) -> int:
        weights = np.array(look.pattern_weights or [1.0] * len(look.patterns), dtype=np.float64)
        bias = dict(self.appearance.pattern_bias)
        weights = weights * np.array([bias.get(p, 1.0) for p in look.patterns])
        return int(rng.choice(len(look.patterns), p=weights / weights.sum()))

    def add(self, look: Look, rng: np.random.Generator, shell: bool = False) -> int:
        """Draw one instance of ``look`` under the family shift and room offset (colour
        choice, per-instance hue, saturation and brightness jitter, pattern); returns its id.

        ``shell``: the look is a wall, floor or ceiling (gets the family's shell tint too).
        The random texture offset makes two instances of a look differ in pattern phase."""
        app, (room_h, room_s, room_v) = self.appearance, self.room
        tint = np.asarray(app.tint) * (np.asarray(app.shell_tint) if shell else 1.0)
        hue = app.hue_deg + room_h + rng.normal(0.0, look.hue_jitter)
        sat = app.saturation * np.exp(room_s + rng.normal(0.0, look.saturation_jitter))
        val = app.value * np.exp(room_v + rng.normal(0.0, look.value_jitter))
        c1 = shift_color(look.colors[int(rng.integers(len(look.colors)))], hue, sat, val, tint)
        if look.secondary:
            c2 = shift_color(
                look.secondary[int(rng.integers(len(look.secondary)))], hue, sat, val, tint
            )
        else:
            c2 = c1 * (1.0 - look.contrast)
        k = self._pick_pattern(look, rng)
        base_scale = look.scales[k] if look.scales else look.scale
        self.pattern.append(PATTERNS.index(look.patterns[k]))
        self.color1.append(c1)
        self.color2.append(c2)
        self.scale.append(base_scale * float(np.exp(rng.normal(0.0, 0.1))))
        self.emission.append(look.emission)
        self.offset.append(rng.uniform(-50.0, 50.0, 3))
        return len(self.pattern) - 1

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "pattern": np.array(self.pattern, dtype=np.int64),
            "color1": np.array(self.color1),
            "color2": np.array(self.color2),
            "scale": np.array(self.scale),
            "emission": np.array(self.emission),
            "offset": np.array(self.offset),
        }


def face_uv(local: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangent coordinates (u, v) and the normal coordinate of points on faces with ``axis``."""
    x, y, z = local[:, 0], local[:, 1], local[:, 2]
    u = np.where(axis == 0, y, x)
    v = np.where(axis == 2, y, z)
    w = np.choose(axis, (x, y, z))
    return u, v, w


def _pattern_weight(
    kind: str, u, v, w, p, s, seed
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Mix weight between the two colours, a brightness factor, and an override mask (mortar)."""
    one = np.ones_like(u)
    if kind == "noise":
        return fbm3(p / s[:, None], 3, seed), one, None
    if kind == "wood":
        warp = fbm3(np.stack([u / (8 * s), v / s, w / s], axis=-1), 2, seed)
        return (0.5 + 0.5 * np.sin(2 * np.pi * (v / s + 3.0 * warp))) ** 2, one, None
    if kind == "planks":
        pw, pl = s, 8.0 * s
        row = np.floor(v / pw)
        uu = u + 7.0 * pl * hash01(row, seed=seed)
        col = np.floor(uu / pl)
        warp = fbm3(np.stack([uu / (6 * pw), v / (0.3 * pw), row], axis=-1), 2, seed)
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (4.0 * warp + v / (0.4 * pw)))
        tint = 0.82 + 0.36 * hash01(row, col, seed=seed + 1)
        seam = (np.mod(v / pw, 1.0) < 0.04) | (np.mod(uu / pl, 1.0) < 0.006)
        return (
            0.6 * grain + 0.4 * hash01(row, col, seed=seed + 2),
            tint * np.where(seam, 0.55, 1.0),
            None,
        )
    if kind == "tiles":
        i, j = np.floor(u / s), np.floor(v / s)
        check = np.mod(i + j, 2.0)
        grout = (np.mod(u / s, 1.0) < 0.02) | (np.mod(v / s, 1.0) < 0.02)
        wgt = (
            0.55 * check
            + 0.25 * hash01(i, j, seed=seed)
            + 0.2 * fbm3(p / (0.1 * s[:, None]), 2, seed)
        )
        return wgt, np.where(grout, 0.8, 1.0), None
    if kind in ("stripes", "hstripes"):
        coord = u if kind == "stripes" else v
        band = np.mod(np.floor(coord / s), 2.0)
        return 0.8 * band + 0.2 * fbm3(p / (0.5 * s[:, None]), 2, seed), one, None
    if kind == "brick":
        bh, bw = 0.3 * s, s
        row = np.floor(v / bh)
        uu = u + 0.5 * bw * np.mod(row, 2.0)
        col = np.floor(uu / bw)
        mortar = (np.mod(v / bh, 1.0) < 0.1) | (np.mod(uu / bw, 1.0) < 0.03)
        grit = 0.85 + 0.3 * fbm3(p / 0.02, 2, seed)
        return hash01(row, col, seed=seed), grit, mortar
    if kind == "spines":
        book = np.floor(u / s)
        shade = 0.6 + 0.55 * hash01(book, seed=seed + 1)
        band = np.abs(np.mod(v, 0.1) - 0.05) < 0.004
        return hash01(book, seed=seed), shade * np.where(band, 0.8, 1.0), None
    if kind == "fabric":
        weave = np.sin(2 * np.pi * u / (0.1 * s)) * np.sin(2 * np.pi * v / (0.1 * s))
        return 0.35 + 0.15 * weave + 0.5 * fbm3(p / s[:, None], 2, seed), one, None
    if kind == "painting":
        f = fbm3(p / s[:, None], 4, seed)
        return (
            np.clip((f - 0.35) / 0.3, 0.0, 1.0),
            0.8 + 0.4 * fbm3(p / (0.3 * s[:, None]), 2, seed + 5),
            None,
        )
    raise ValueError(f"unknown texture pattern {kind!r}")


def albedo(
    mats: dict[str, np.ndarray], mat_id: np.ndarray, local: np.ndarray, axis: np.ndarray
) -> np.ndarray:
    """Linear albedo (n, 3) at points ``local`` (n, 3) on faces ``axis`` of materials ``mat_id``."""
    out = np.zeros((len(mat_id), 3))
    kinds = mats["pattern"][mat_id]
    for k in np.unique(kinds):
        sel = np.nonzero(kinds == k)[0]
        m = mat_id[sel]
        p = local[sel] + mats["offset"][m]
        u, v, w = face_uv(p, axis[sel])
        s = mats["scale"][m]
        # One seed per pattern keeps evaluation vectorised; materials differ by their offset.
        seed = 17 + 101 * int(k)
        wgt, bright, override = _pattern_weight(PATTERNS[k], u, v, w, p, s, seed)
        wgt = np.clip(wgt, 0.0, 1.0)[:, None]
        col = (1.0 - wgt) * mats["color1"][m] + wgt * mats["color2"][m]
        col = col * bright[:, None]
        if override is not None:
            col[override] = 0.5 * (_MORTAR + mats["color1"][m[override]]) * bright[override, None]
        out[sel] = col
    return np.clip(out, 0.0, 1.0)
