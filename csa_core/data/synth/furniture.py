"""Furniture made of boxes and round rods, each builder returning a group in its own frame.

Pieces have real proportions: legs, posts and spindles 1-3 cm across, boards 1.5-2.5 cm
thick, gaps between slats, backs that lean, bars that bend (chains of rods, :func:`arc`).

Group frame: metres, z up, floor at z = 0, the footprint centred on the origin, the front
facing -y and the back (the side that goes against a wall) at +y. Every part carries its
NYU40 class name and a material role ("body", "top", "frame", "soft", "screen", "glass",
"shade", "canvas", "stem", "leaf"); the family decides what each (class, role) looks like.
Builders keep parts of different objects apart by construction (parts of one object may
join, as a spindle set into a seat), so objects never interpenetrate; the layout keeps
groups apart.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

Rng = np.random.Generator
Extents = tuple[tuple[float, float, float], tuple[float, float, float]]  # (min xyz, max xyz)


@dataclass(frozen=True)
class Part:
    """One solid of a group: centre and half-extents in the group frame, orientation
    ``Rz(yaw) @ Rx(tilt)`` (yaw about +z after a tilt about the part's own x axis).

    ``shape`` "box": a box with those half-extents. ``shape`` "rod": a capsule (round rod with
    rounded ends, :mod:`csa_core.data.synth.solids`) of radius ``half[0]`` around a segment of
    length ``2 * half[2]`` along the part's own z axis; make one with :func:`rod`.
    """

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    label: str
    role: str = "body"
    yaw: float = 0.0
    instance: int = 0  # parts of one group with the same (label, role, instance) share a material
    tilt: float = 0.0
    shape: str = "box"

    def rotation(self) -> np.ndarray:
        """Part-to-group rotation (3, 3)."""
        cy, sy, ct, st = (
            math.cos(self.yaw),
            math.sin(self.yaw),
            math.cos(self.tilt),
            math.sin(self.tilt),
        )
        return np.array([[cy, -sy * ct, sy * st], [sy, cy * ct, -cy * st], [0.0, st, ct]])

    def extent(self) -> np.ndarray:
        """Half-extents (3,) of the part's axis-aligned bounds in the group frame."""
        rot = self.rotation()
        if self.shape == "rod":
            return np.abs(rot[:, 2]) * self.half[2] + self.half[0]
        return np.abs(rot) @ np.asarray(self.half)

    def planar_half(self) -> tuple[float, float]:
        """Half-extents of the part's floor footprint along its own yawed x and y axes."""
        ct, st = abs(math.cos(self.tilt)), abs(math.sin(self.tilt))
        if self.shape == "rod":
            return self.half[0], st * self.half[2] + self.half[0]
        return self.half[0], ct * self.half[1] + st * self.half[2]


@dataclass(frozen=True)
class Group:
    """A placeable set of parts. ``mount``: "wall" (back against a wall, on the floor),
    "free" (anywhere on the floor, any yaw) or "onwall" (hung on a wall)."""

    kind: str
    parts: tuple[Part, ...]
    mount: str
    keepout: Extents | None = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of all parts in the group frame."""
        lo, hi = _parts_bounds(self.parts)
        if self.keepout is not None:
            lo, hi = np.minimum(lo, self.keepout[0]), np.maximum(hi, self.keepout[1])
        return lo, hi


def box(
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    z0: float,
    z1: float,
    label: str,
    role: str = "body",
    instance: int = 0,
) -> Part:
    """A part from its extents along x, y and z."""
    return Part(
        ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
        ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
        label,
        role,
        0.0,
        instance,
    )


def rod(
    p0: tuple[float, float, float],
    p1: tuple[float, float, float],
    radius: float,
    label: str,
    role: str = "frame",
    instance: int = 0,
) -> Part:
    """A round rod (capsule) of ``radius`` around the segment p0-p1; its rounded ends reach
    ``radius`` beyond the end points."""
    a, b = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    d = b - a
    length = float(np.linalg.norm(d))
    u = d / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    tilt = math.acos(max(-1.0, min(1.0, float(u[2]))))
    yaw = math.atan2(u[0], -u[1]) if math.sin(tilt) > 1e-9 else 0.0
    centre = tuple(float(v) for v in (a + b) / 2)
    return Part(centre, (radius, radius, length / 2), label, role, yaw, instance, tilt, "rod")


def arc(
    centre: tuple[float, float, float],
    radius: float,
    a0: float,
    a1: float,
    plane: str,
    pieces: int,
    thickness: float,
    label: str,
    role: str = "frame",
    instance: int = 0,
) -> list[Part]:
    """A curved rod: ``pieces`` capsules joined end to end along a circular arc of ``radius``
    from angle ``a0`` to ``a1`` (radians) around ``centre``, in the "xy" (horizontal) or
    "yz"/"xz" (vertical) plane; the joints are round, so the chain bends smoothly."""
    ang = np.linspace(a0, a1, pieces + 1)
    cx, cy, cz = centre
    if plane == "xy":
        pts = [(cx + radius * math.cos(t), cy + radius * math.sin(t), cz) for t in ang]
    elif plane == "xz":
        pts = [(cx + radius * math.cos(t), cy, cz + radius * math.sin(t)) for t in ang]
    else:
        pts = [(cx, cy + radius * math.cos(t), cz + radius * math.sin(t)) for t in ang]
    return [rod(pts[k], pts[k + 1], thickness, label, role, instance) for k in range(pieces)]


def slab(
    center: tuple[float, float, float],
    half: tuple[float, float, float],
    tilt: float,
    label: str,
    role: str = "body",
    instance: int = 0,
) -> Part:
    """A box tilted by ``tilt`` radians about its own x axis (its top leans towards +y for a
    positive tilt)."""
    return Part(center, half, label, role, 0.0, instance, -tilt)


def _parts_bounds(parts: tuple[Part, ...] | list[Part]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for p in parts:
        ext = p.extent()
        lo = np.minimum(lo, np.asarray(p.center) - ext)
        hi = np.maximum(hi, np.asarray(p.center) + ext)
    return lo, hi


def moved(
    parts: list[Part] | tuple[Part, ...],
    dx: float,
    dy: float,
    yaw: float = 0.0,
    dz: float = 0.0,
    instance: int | None = None,
) -> list[Part]:
    """Parts rotated by ``yaw`` about the origin, then shifted by (dx, dy, dz)."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for p in parts:
        x, y, z = p.center
        inst = p.instance if instance is None else instance
        out.append(
            replace(
                p,
                center=(c * x - s * y + dx, s * x + c * y + dy, z + dz),
                yaw=p.yaw + yaw,
                instance=inst,
            )
        )
    return out


def make_group(kind: str, parts: list[Part], mount: str, keepout: Extents | None = None) -> Group:
    """A group with its footprint recentred on the origin (keepout included)."""
    lo, hi = _parts_bounds(parts)
    if keepout is not None:
        lo, hi = np.minimum(lo, keepout[0]), np.maximum(hi, keepout[1])
    cx, cy = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
    parts = moved(parts, -cx, -cy)
    if keepout is not None:
        keepout = (
            (keepout[0][0] - cx, keepout[0][1] - cy, keepout[0][2]),
            (keepout[1][0] - cx, keepout[1][1] - cy, keepout[1][2]),
        )
    return Group(kind, tuple(parts), mount, keepout)


def _u(rng: Rng, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


# ---- single pieces (front at -y, footprint centred) -------------------------------------


TABLE_LEGS = ("square", "round", "hairpin")


def table_parts(
    rng: Rng, w: float, d: float, h: float, instance: int = 0, legs: str | None = None
) -> list[Part]:
    """A table top 2-3.5 cm thick on four legs: square wooden legs 3.5-5 cm with an apron,
    round metal legs 2.4-3.2 cm across, or hairpin legs (two 1.2 cm rods in a V each)."""
    legs = legs or str(rng.choice(TABLE_LEGS, p=(0.45, 0.35, 0.2)))
    top = _u(rng, 0.02, 0.035)
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, h - top, h, "table", "top", instance)]
    inset = _u(rng, 0.03, 0.08)
    for sx in (-1, 1):
        for sy in (-1, 1):
            if legs == "square":
                leg = _u(rng, 0.035, 0.05) if sx == sy == -1 else parts[1].half[0] * 2
                x, y = sx * (w / 2 - inset - leg / 2), sy * (d / 2 - inset - leg / 2)
                parts.append(
                    box(
                        x - leg / 2,
                        x + leg / 2,
                        y - leg / 2,
                        y + leg / 2,
                        0.0,
                        h - top,
                        "table",
                        "frame",
                        instance,
                    )
                )
            elif legs == "round":
                r = _u(rng, 0.012, 0.016) if sx == sy == -1 else parts[1].half[0]
                x, y = sx * (w / 2 - inset - r), sy * (d / 2 - inset - r)
                parts.append(rod((x, y, r), (x, y, h - top - r), r, "table", "frame", instance))
            else:
                r = 0.006
                x, y = sx * (w / 2 - inset - r), sy * (d / 2 - inset - r)
                foot = (x, y, r)
                for dx in (0.0, 0.12):
                    parts.append(
                        rod(foot, (x - sx * dx, y, h - top - r), r, "table", "frame", instance)
                    )
    if legs == "square":
        apron, t = _u(rng, 0.06, 0.1), 0.02
        leg = parts[1].half[0] * 2
        xi, yi = w / 2 - inset - leg, d / 2 - inset - leg
        for sy in (-1, 1):
            y = sy * (d / 2 - inset - leg / 2)
            parts.append(
                box(
                    -xi,
                    xi,
                    y - t / 2,
                    y + t / 2,
                    h - top - apron,
                    h - top,
                    "table",
                    "frame",
                    instance,
                )
            )
        for sx in (-1, 1):
            x = sx * (w / 2 - inset - leg / 2)
            parts.append(
                box(
                    x - t / 2,
                    x + t / 2,
                    -yi,
                    yi,
                    h - top - apron,
                    h - top,
                    "table",
                    "frame",
                    instance,
                )
            )
    return parts


CHAIR_STYLES = ("slat", "ladder", "spindle", "tube", "upholstered")


def chair_design(rng: Rng, style: str | None = None) -> dict:
    """Proportions of one chair model (a dining set repeats it): style, seat size and height,
    back height and lean, leg and slat sizes."""
    style = style or str(rng.choice(CHAIR_STYLES, p=(0.25, 0.15, 0.2, 0.2, 0.2)))
    return {
        "style": style,
        "w": _u(rng, 0.40, 0.48),
        "d": _u(rng, 0.40, 0.46),
        "seat_h": _u(rng, 0.44, 0.47),
        "seat_t": _u(rng, 0.05, 0.07) if style == "upholstered" else _u(rng, 0.02, 0.035),
        "back_h": _u(rng, 0.38, 0.5),
        "lean": math.radians(_u(rng, 6.0, 14.0)),
        "leg": _u(rng, 0.022, 0.03),  # square leg side, or rod diameter
        "slats": int(rng.integers(3, 6)),
        "slat_w": _u(rng, 0.02, 0.045),
        "rails": int(rng.integers(2, 5)),
        "spindles": int(rng.integers(5, 8)),
        "spindle_r": _u(rng, 0.006, 0.009),
        "stretchers": bool(rng.random() < 0.6),
    }


def _back_point(y0: float, z0: float, lean: float, s: float) -> tuple[float, float]:
    """(y, z) at distance ``s`` up a chair back leaning back by ``lean`` from (y0, z0)."""
    return y0 + s * math.sin(lean), z0 + s * math.cos(lean)


def chair_parts(rng: Rng, instance: int = 0, design: dict | None = None) -> list[Part]:
    """A chair, front at -y, about 0.45 m wide: a seat on legs 2-3 cm thick and a back leaning
    back 6-14 degrees that is open: vertical slats, horizontal rails or round spindles under a
    curved crest rail with gaps between them, a metal tube frame holding a back panel above the
    seat, or (upholstered) a padded back on thin legs."""
    g = design or chair_design(rng)
    style, w, d, sh, st = g["style"], g["w"], g["d"], g["seat_h"], g["seat_t"]
    back_h, lean, leg = g["back_h"], g["lean"], g["leg"]
    soft = "soft" if style == "upholstered" else "body"
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, sh - st, sh, "chair", soft, instance)]
    r = leg / 2
    under = sh - st
    yb = d / 2 - 0.015 - r  # back legs and posts
    if style == "spindle":
        splay = 0.035
        for sx in (-1, 1):
            for sy in (-1, 1):
                top = (sx * (w / 2 - 0.06), sy * (d / 2 - 0.06), under - r)
                parts.append(
                    rod(
                        (top[0] + sx * splay, top[1] + sy * splay, r),
                        top,
                        r,
                        "chair",
                        "frame",
                        instance,
                    )
                )
        if g["stretchers"]:
            z = 0.16
            for sx in (-1, 1):
                x = sx * (w / 2 - 0.06 + splay * (1 - z / under))
                parts.append(
                    rod(
                        (x, -(d / 2 - 0.06) - 0.02, z),
                        (x, d / 2 - 0.06 + 0.02, z),
                        0.008,
                        "chair",
                        "frame",
                        instance,
                    )
                )
        # Crest rail: a horizontal bow whose middle sits back_h above the seat, leaning back.
        rr = g["spindle_r"]
        yc, zc = _back_point(d / 2 - 0.05, sh, lean, back_h)
        bow_r = _u(rng, 0.45, 0.7)
        half_ang = math.asin(min(0.95, (w / 2 - 0.02) / bow_r))
        centre = (0.0, yc - bow_r, zc)
        parts += arc(
            centre,
            bow_r,
            math.pi / 2 - half_ang,
            math.pi / 2 + half_ang,
            "xy",
            6,
            0.014,
            "chair",
            "frame",
            instance,
        )
        n = g["spindles"]
        for k in range(n):
            ang = math.pi / 2 - half_ang + (k + 0.5) / n * 2 * half_ang
            x_top, y_top = bow_r * math.cos(ang), yc - bow_r + bow_r * math.sin(ang)
            x_bot = x_top * 0.85
            parts.append(
                rod(
                    (x_bot, d / 2 - 0.05 - (yc - y_top), sh + rr),
                    (x_top, y_top, zc),
                    rr,
                    "chair",
                    "frame",
                    instance,
                )
            )
        return parts
    if style == "tube":
        rt = max(0.009, min(0.012, r))
        for sx in (-1, 1):
            x = sx * (w / 2 - 0.02)
            parts.append(
                rod(
                    (x, -(d / 2 - 0.02), rt),
                    (x, -(d / 2 - 0.02), under - rt),
                    rt,
                    "chair",
                    "frame",
                    instance,
                )
            )
            # Rear leg and back post: one bent tube, vertical under the seat, leaning above it.
            parts.append(
                rod((x, d / 2 - 0.02, rt), (x, d / 2 - 0.02, sh), rt, "chair", "frame", instance)
            )
            yt, zt = _back_point(d / 2 - 0.02, sh, lean, back_h)
            parts.append(rod((x, d / 2 - 0.02, sh), (x, yt, zt), rt, "chair", "frame", instance))
        panel_h = _u(rng, 0.14, 0.22)
        s0 = back_h - panel_h
        y_mid, z_mid = _back_point(d / 2 - 0.02 - rt - 0.008, sh, lean, s0 + panel_h / 2)
        parts.append(
            Part(
                (0.0, y_mid, z_mid),
                (w / 2 - 0.02 - rt, 0.007, panel_h / 2),
                "chair",
                "body",
                0.0,
                instance,
                -lean,
            )
        )
        return parts
    # Square legs; the back legs continue as posts leaning back above the seat.
    for sx in (-1, 1):
        x = sx * (w / 2 - 0.015 - r)
        parts.append(
            box(
                x - r,
                x + r,
                -d / 2 + 0.015,
                -d / 2 + 0.015 + leg,
                0.0,
                under,
                "chair",
                "frame",
                instance,
            )
        )
        parts.append(box(x - r, x + r, yb - r, yb + r, 0.0, under, "chair", "frame", instance))
        y_mid, z_mid = _back_point(yb, sh, lean, back_h / 2)
        parts.append(
            Part((x, y_mid, z_mid), (r, r, back_h / 2), "chair", "frame", 0.0, instance, -lean)
        )
        if g["stretchers"]:
            parts.append(
                rod(
                    (x, -d / 2 + 0.03 + leg, 0.15),
                    (x, yb - r - 0.01, 0.15),
                    0.008,
                    "chair",
                    "frame",
                    instance,
                )
            )
    inner = w / 2 - 0.015 - leg  # between the posts
    t = 0.018
    if style == "upholstered":
        y_mid, z_mid = _back_point(yb, sh, lean, 0.08 + (back_h - 0.08) / 2)
        parts.append(
            Part(
                (0.0, y_mid, z_mid),
                (inner, 0.03, (back_h - 0.08) / 2),
                "chair",
                soft,
                0.0,
                instance,
                -lean,
            )
        )
        return parts
    crest = _u(rng, 0.05, 0.09)
    y_mid, z_mid = _back_point(yb, sh, lean, back_h - crest / 2)
    parts.append(
        Part((0.0, y_mid, z_mid), (inner, t / 2, crest / 2), "chair", "body", 0.0, instance, -lean)
    )
    if style == "ladder":
        n = g["rails"]
        for k in range(n):
            s = 0.1 + k * (back_h - crest - 0.1) / n
            y_mid, z_mid = _back_point(yb, sh, lean, s + 0.02)
            parts.append(
                Part(
                    (0.0, y_mid, z_mid), (inner, t / 2, 0.02), "chair", "body", 0.0, instance, -lean
                )
            )
        return parts
    rail = 0.04
    y_mid, z_mid = _back_point(yb, sh, lean, 0.08 + rail / 2)
    parts.append(
        Part((0.0, y_mid, z_mid), (inner, t / 2, rail / 2), "chair", "body", 0.0, instance, -lean)
    )
    n, sw = g["slats"], g["slat_w"]
    slat_h = back_h - crest - 0.08 - rail
    xs = np.linspace(-inner, inner, n + 2)[1:-1]
    for x in xs:
        y_mid, z_mid = _back_point(yb, sh, lean, 0.08 + rail + slat_h / 2)
        parts.append(
            Part(
                (float(x), y_mid, z_mid),
                (min(sw / 2, inner / (n + 1) / 2 - 0.004), t / 2 - 0.002, slat_h / 2),
                "chair",
                "body",
                0.0,
                instance,
                -lean,
            )
        )
    return parts


def office_chair_parts(rng: Rng, instance: int = 0) -> list[Part]:
    """A swivel chair, front at -y: five castors on a five-star base of 1.5-2 cm spokes, a
    gas lift, a padded seat, a back leaning 10-18 degrees on a curved bar, often armrests on
    thin posts."""
    base_r, castor = _u(rng, 0.28, 0.32), _u(rng, 0.022, 0.027)
    spoke = _u(rng, 0.008, 0.011)
    hub_z = 2 * castor + 0.045
    spin = _u(rng, 0.0, 2 * math.pi / 5)
    parts = []
    for k in range(5):
        a = spin + 2 * math.pi * k / 5
        c, s = math.cos(a), math.sin(a)
        parts.append(
            rod(
                (0.02 * c, 0.02 * s, hub_z),
                (base_r * c, base_r * s, 2 * castor + spoke),
                spoke,
                "chair",
                "frame",
                instance,
            )
        )
        parts.append(
            rod(
                (base_r * c, base_r * s, castor),
                (base_r * c, base_r * s, castor),
                castor,
                "chair",
                "frame",
                instance,
            )
        )
    w, d, sh, st = _u(rng, 0.46, 0.52), _u(rng, 0.44, 0.5), _u(rng, 0.44, 0.52), _u(rng, 0.06, 0.09)
    lift = _u(rng, 0.022, 0.028)
    parts.append(
        rod(
            (0.0, 0.0, hub_z - 0.02),
            (0.0, 0.0, sh - st - 0.05 - lift),
            lift,
            "chair",
            "frame",
            instance,
        )
    )
    parts.append(box(-0.1, 0.1, -0.12, 0.12, sh - st - 0.05, sh - st, "chair", "frame", instance))
    parts.append(box(-w / 2, w / 2, -d / 2, d / 2, sh - st, sh, "chair", "soft", instance))
    lean = math.radians(_u(rng, 10.0, 18.0))
    back_h, gap = _u(rng, 0.42, 0.62), _u(rng, 0.06, 0.14)
    bw, bt = w * _u(rng, 0.85, 0.98), _u(rng, 0.04, 0.06)
    yb = d / 2 + 0.04
    y_mid, z_mid = _back_point(yb, sh, lean, gap + back_h / 2)
    parts.append(
        Part(
            (0.0, y_mid, z_mid), (bw / 2, bt / 2, back_h / 2), "chair", "soft", 0.0, instance, -lean
        )
    )
    # The support: a bar bent in a quarter circle from under the seat up behind the back.
    y_low, z_low = _back_point(yb + bt / 2 + 0.012, sh, lean, gap + 0.06)
    bend = z_low - (sh - st - 0.03)
    parts += arc(
        (0.0, y_low - bend, z_low),
        bend,
        0.0,
        -math.pi / 2,
        "yz",
        4,
        0.012,
        "chair",
        "frame",
        instance,
    )
    parts.append(
        rod(
            (0.0, y_low - bend, sh - st - 0.03),
            (0.0, 0.1, sh - st - 0.03),
            0.012,
            "chair",
            "frame",
            instance,
        )
    )
    if rng.random() < 0.7:
        arm_h = _u(rng, 0.18, 0.25)
        for sx in (-1, 1):
            x = sx * (w / 2 + 0.03)
            parts.append(
                rod(
                    (x, 0.05, sh - st - 0.01),
                    (x, 0.05, sh + arm_h - 0.012),
                    0.011,
                    "chair",
                    "frame",
                    instance,
                )
            )
            parts.append(
                box(
                    x - 0.035,
                    x + 0.035,
                    -0.1,
                    0.15,
                    sh + arm_h,
                    sh + arm_h + 0.03,
                    "chair",
                    "soft",
                    instance,
                )
            )
    return parts


def stool_parts(rng: Rng, instance: int = 0, bar: bool | None = None) -> list[Part]:
    """A stool: a seat board on four splayed round legs 2-3 cm across joined by a foot ring
    of thin rungs; a bar stool (65-78 cm) or a low one (45 cm)."""
    bar = bool(rng.random() < 0.6) if bar is None else bar
    h = _u(rng, 0.65, 0.78) if bar else _u(rng, 0.43, 0.48)
    side, t = _u(rng, 0.3, 0.38), _u(rng, 0.025, 0.04)
    r, splay = _u(rng, 0.01, 0.015), _u(rng, 0.04, 0.07) * (h / 0.7)
    parts = [box(-side / 2, side / 2, -side / 2, side / 2, h - t, h, "chair", "body", instance)]
    inner = side / 2 - 0.04
    feet = []
    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        top = (sx * inner, sy * inner, h - t - r)
        foot = (sx * (inner + splay), sy * (inner + splay), r)
        parts.append(rod(foot, top, r, "chair", "frame", instance))
        feet.append((np.asarray(foot), np.asarray(top)))
    z = _u(rng, 0.22, 0.3) if bar else 0.15
    ring = [f + (tp - f) * ((z - f[2]) / (tp[2] - f[2])) for f, tp in feet]
    for k in range(4):
        parts.append(
            rod(tuple(ring[k]), tuple(ring[(k + 1) % 4]), 0.008, "chair", "frame", instance)
        )
    return parts


def lamp_parts(rng: Rng, floor: bool, z0: float = 0.0, instance: int = 0) -> list[Part]:
    """A lamp standing at ``z0``: a floor lamp (a 2-2.6 cm pole on a thin round base or on
    three splayed legs, under a shade) or a small table lamp on a thin stem."""
    frame = "frame"
    if not floor:
        base, pole_h, shade_w, shade_h = (
            _u(rng, 0.1, 0.15),
            _u(rng, 0.2, 0.3),
            _u(rng, 0.18, 0.25),
            _u(rng, 0.14, 0.2),
        )
        r = _u(rng, 0.006, 0.01)
        return [
            box(-base / 2, base / 2, -base / 2, base / 2, z0, z0 + 0.02, "lamp", frame, instance),
            rod((0.0, 0.0, z0 + 0.02), (0.0, 0.0, z0 + 0.02 + pole_h), r, "lamp", frame, instance),
            box(
                -shade_w / 2,
                shade_w / 2,
                -shade_w / 2,
                shade_w / 2,
                z0 + 0.02 + pole_h,
                z0 + 0.02 + pole_h + shade_h,
                "lamp",
                "shade",
                instance,
            ),
        ]
    pole_h, shade_w, shade_h = _u(rng, 1.25, 1.5), _u(rng, 0.3, 0.45), _u(rng, 0.25, 0.35)
    r = _u(rng, 0.01, 0.013)
    if rng.random() < 0.5:
        base = _u(rng, 0.25, 0.32)
        parts = [
            box(-base / 2, base / 2, -base / 2, base / 2, z0, z0 + 0.015, "lamp", frame, instance)
        ]
        z_pole = z0 + 0.015
    else:
        z_pole = z0 + _u(rng, 0.5, 0.7)
        spread = _u(rng, 0.2, 0.28)
        parts = []
        for k in range(3):
            a = 2 * math.pi * k / 3 + 0.3
            parts.append(
                rod(
                    (spread * math.cos(a), spread * math.sin(a), z0 + 0.01),
                    (0.0, 0.0, z_pole),
                    0.01,
                    "lamp",
                    frame,
                    instance,
                )
            )
    parts.append(rod((0.0, 0.0, z_pole), (0.0, 0.0, z0 + pole_h), r, "lamp", frame, instance))
    parts.append(
        box(
            -shade_w / 2,
            shade_w / 2,
            -shade_w / 2,
            shade_w / 2,
            z0 + pole_h + r,
            z0 + pole_h + r + shade_h,
            "lamp",
            "shade",
            instance,
        )
    )
    return parts


def arc_lamp(rng: Rng) -> Group:
    """An arc floor lamp: a heavy base, a 2.4 cm rod rising and curving over in a wide arc,
    and a round shade hanging at its end."""
    base, reach = _u(rng, 0.3, 0.38), _u(rng, 0.8, 1.2)
    rise, r = _u(rng, 1.0, 1.3), 0.012
    parts = [box(-base / 2, base / 2, -base / 2, base / 2, 0.0, 0.05, "lamp", "frame")]
    bend = reach / 2
    parts.append(rod((0.0, 0.0, 0.05), (0.0, 0.0, rise), r, "lamp", "frame"))
    parts += arc((0.0, -bend, rise), bend, 0.0, math.pi * 0.85, "yz", 8, r, "lamp", "frame")
    tip_y, tip_z = -bend + bend * math.cos(math.pi * 0.85), rise + bend * math.sin(math.pi * 0.85)
    shade_r = _u(rng, 0.14, 0.2)
    parts.append(
        rod(
            (0.0, tip_y, tip_z - r - shade_r),
            (0.0, tip_y, tip_z - r - shade_r),
            shade_r,
            "lamp",
            "shade",
        )
    )
    return make_group("arc_lamp", parts, "wall")


def plant(rng: Rng) -> Group:
    """A potted plant (NYU40 "otherprop"): a pot, thin stems 1-2 cm fanning out and leaves
    on them, or a small tree with a trunk and thin branches."""
    pot_w, pot_h = _u(rng, 0.22, 0.4), _u(rng, 0.22, 0.4)
    parts = [box(-pot_w / 2, pot_w / 2, -pot_w / 2, pot_w / 2, 0.0, pot_h, "otherprop", "body")]
    tree = rng.random() < 0.4
    if tree:
        height = _u(rng, 1.3, 1.8)
        parts.append(
            rod((0.0, 0.0, pot_h + 0.01), (0.0, 0.0, height * 0.6), 0.012, "otherprop", "stem")
        )
        starts = [(0.0, 0.0, height * _u(rng, 0.4, 0.6)) for _ in range(int(rng.integers(4, 7)))]
        length = (0.35, 0.6)
    else:
        starts = [(0.0, 0.0, pot_h + 0.01) for _ in range(int(rng.integers(6, 11)))]
        length = (0.3, 0.6)
    for p0 in starts:
        a, up = _u(rng, 0, 2 * math.pi), _u(rng, 0.3, 1.2)
        ln = _u(rng, *length)
        tip = (
            p0[0] + ln * math.cos(up) * math.cos(a),
            p0[1] + ln * math.cos(up) * math.sin(a),
            p0[2] + ln * math.sin(up),
        )
        parts.append(rod(p0, tip, _u(rng, 0.004, 0.008), "otherprop", "stem"))
        lw, ll = _u(rng, 0.04, 0.09), _u(rng, 0.12, 0.22)
        parts.append(
            Part(
                tip,
                (lw / 2, 0.003, ll / 2),
                "otherprop",
                "leaf",
                a + math.pi / 2,
                0,
                _u(rng, 0.3, 1.2),
            )
        )
    return make_group("plant", parts, "wall")


def book_rows(
    rng: Rng, x0: float, x1: float, y0: float, y1: float, z0: float, max_h: float, instance: int = 0
) -> list[Part]:
    """One or two runs of books standing on a board between x0 and x1."""
    parts = []
    width = x1 - x0
    fill = _u(rng, 0.4, 0.95) * width
    start = x0 + _u(rng, 0.0, width - fill)
    runs = 2 if fill > 0.5 and rng.random() < 0.5 else 1
    edges = np.linspace(start, start + fill, runs + 1)
    for k in range(runs):
        a, b = edges[k] + (0.01 if k else 0.0), edges[k + 1]
        h = min(max_h, _u(rng, 0.17, 0.3))
        parts.append(
            box(
                a,
                b,
                y0,
                y0 + min(y1 - y0, _u(rng, 0.15, 0.24)),
                z0,
                z0 + h,
                "books",
                "body",
                instance,
            )
        )
    return parts


def cardboard_boxes(
    rng: Rng, x0: float, x1: float, y0: float, y1: float, z0: float, max_h: float, instance: int = 0
) -> list[Part]:
    """A row of boxes on a board or the floor, side by side without touching."""
    parts = []
    x = x0 + _u(rng, 0.0, 0.1)
    k = 0
    while True:
        w = _u(rng, 0.25, 0.5)
        if x + w > x1:
            break
        d = min(y1 - y0, _u(rng, 0.25, 0.45))
        h = min(max_h, _u(rng, 0.18, 0.4))
        if rng.random() < 0.75:
            parts.append(box(x, x + w, y0, y0 + d, z0, z0 + h, "box", "body", instance + k))
        x += w + _u(rng, 0.02, 0.12)
        k += 1
    return parts


# ---- groups -------------------------------------------------------------------------------


def dining_set(rng: Rng) -> Group:
    """A table with matching chairs around it facing it, free-standing."""
    w, d = _u(rng, 1.0, 1.8), _u(rng, 0.75, 1.0)
    parts = table_parts(rng, w, d, _u(rng, 0.72, 0.77))
    design = chair_design(rng)
    per_side = 2 if w > 1.35 else 1
    inst = 1
    for side in (-1, 1):
        xs = np.linspace(-w / 4, w / 4, per_side) if per_side == 2 else [0.0]
        for x in xs:
            if rng.random() < 0.85:
                yaw = (0.0 if side > 0 else math.pi) + _u(rng, -0.2, 0.2)
                parts += moved(chair_parts(rng, inst, design), float(x), side * (d / 2 + 0.38), yaw)
                inst += 1
    if rng.random() < 0.5:
        parts += moved(
            chair_parts(rng, inst, design), -(w / 2 + 0.38), 0.0, math.pi / 2 + _u(rng, -0.2, 0.2)
        )
    return make_group("dining", parts, "free")


def dining_by_wall(rng: Rng) -> Group:
    """A smaller dining table pushed against a wall with two to four matching chairs on its
    free sides: where a free-standing set does not fit (``FALLBACKS``)."""
    w, d = _u(rng, 0.8, 1.3), _u(rng, 0.65, 0.85)
    parts = table_parts(rng, w, d, _u(rng, 0.72, 0.77))
    design = chair_design(rng)
    spots = [(x, -(d / 2 + 0.38), math.pi) for x in ((-w / 4, w / 4) if w > 1.05 else (0.0,))]
    spots += [(sx * (w / 2 + 0.38), 0.0, -sx * math.pi / 2) for sx in (-1, 1)]
    inst = 1
    for x, y, yaw in spots:
        if inst == 1 or rng.random() < 0.75:
            parts += moved(chair_parts(rng, inst, design), x, y, yaw + _u(rng, -0.15, 0.15))
            inst += 1
    return make_group("dining", parts, "wall")


def meeting_set(rng: Rng) -> Group:
    """A meeting table on thin legs with four to eight swivel chairs (or metal tube chairs)
    around it, free-standing."""
    w, d = _u(rng, 1.6, 2.4), _u(rng, 0.9, 1.1)
    parts = table_parts(rng, w, d, _u(rng, 0.72, 0.76), legs=str(rng.choice(["round", "square"])))
    swivel = rng.random() < 0.75
    design = chair_design(rng, "tube")
    per_side = 3 if w > 2.0 else 2
    inst = 1
    for side in (-1, 1):
        for x in np.linspace(-w / 3, w / 3, per_side):
            if rng.random() < 0.9:
                yaw = (0.0 if side > 0 else math.pi) + _u(rng, -0.3, 0.3)
                chair = office_chair_parts(rng, inst) if swivel else chair_parts(rng, inst, design)
                parts += moved(chair, float(x), side * (d / 2 + 0.45), yaw)
                inst += 1
    return make_group("meeting", parts, "free")


def loose_chairs(rng: Rng) -> Group:
    """One or two chairs standing on their own by a wall, facing into the room."""
    swivel = rng.random() < 0.4
    design = chair_design(rng)
    parts: list[Part] = []
    for k in range(int(rng.integers(1, 3))):
        chair = office_chair_parts(rng, k) if swivel else chair_parts(rng, k, design)
        parts += moved(chair, 0.75 * k, _u(rng, -0.1, 0.1), _u(rng, -0.6, 0.6))
    return make_group("chairs", parts, "wall")


def stool_row(rng: Rng) -> Group:
    """Two to four stools of one kind in a row."""
    bar = bool(rng.random() < 0.6)
    parts: list[Part] = []
    model = int(rng.integers(2**31))  # one model: every stool is built from the same draws
    for k in range(int(rng.integers(2, 5))):
        parts += moved(
            stool_parts(np.random.default_rng(model), k, bar), 0.55 * k, 0.0, _u(rng, -0.4, 0.4)
        )
    return make_group("stools", parts, "wall")


def _desk_top(rng: Rng, w: float, d: float, h: float, frame: bool) -> list[Part]:
    """A desk: a top on two side panels (sometimes a drawer unit), or on a metal frame of
    square legs 2.5-3.5 cm with a rear crossbar."""
    t = _u(rng, 0.02, 0.035)
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, h - t, h, "desk", "top")]
    if frame:
        leg = _u(rng, 0.025, 0.035)
        for sx in (-1, 1):
            x = sx * (w / 2 - 0.04 - leg / 2)
            for sy in (-1, 1):
                y = sy * (d / 2 - 0.04 - leg / 2)
                parts.append(
                    box(
                        x - leg / 2,
                        x + leg / 2,
                        y - leg / 2,
                        y + leg / 2,
                        0.0,
                        h - t,
                        "desk",
                        "body",
                    )
                )
            parts.append(
                box(
                    x - leg / 2,
                    x + leg / 2,
                    -d / 2 + 0.04 + leg,
                    d / 2 - 0.04 - leg,
                    0.05,
                    0.05 + leg,
                    "desk",
                    "body",
                )
            )
        x_in = w / 2 - 0.04 - leg
        y = d / 2 - 0.04 - leg / 2
        parts.append(
            rod(
                (-x_in + 0.011, y, h - t - 0.1),
                (x_in - 0.011, y, h - t - 0.1),
                0.011,
                "desk",
                "body",
            )
        )
        return parts
    side = _u(rng, 0.018, 0.03)
    parts += [
        box(-w / 2, -w / 2 + side, -d / 2 + 0.02, d / 2, 0.0, h - t, "desk", "body"),
        box(w / 2 - side, w / 2, -d / 2 + 0.02, d / 2, 0.0, h - t, "desk", "body"),
    ]
    if rng.random() < 0.6:
        dw = _u(rng, 0.35, 0.45)
        parts.append(
            box(
                w / 2 - side - dw,
                w / 2 - side - 0.005,
                -d / 2 + 0.03,
                d / 2,
                h - t - 0.45,
                h - t,
                "desk",
                "body",
            )
        )
    return parts


def desk_set(rng: Rng, office: bool = False) -> Group:
    """A desk against a wall, its chair in front (a swivel chair in an office), a lamp,
    books, a screen."""
    w, d, h = _u(rng, 1.1, 1.6), _u(rng, 0.6, 0.75), _u(rng, 0.72, 0.76)
    parts = _desk_top(rng, w, d, h, frame=rng.random() < (0.7 if office else 0.4))
    side_sign = float(rng.choice([-1, 1]))
    if rng.random() < 0.7:
        parts += moved(lamp_parts(rng, floor=False, z0=h), side_sign * (w / 2 - 0.15), d / 2 - 0.15)
    if rng.random() < 0.7:
        edge = -side_sign * (w / 2 - 0.03)
        parts += book_rows(
            rng,
            min(edge, edge + 0.3 * side_sign),
            max(edge, edge + 0.3 * side_sign),
            d / 2 - 0.28,
            d / 2 - 0.02,
            h,
            0.3,
        )
    if (w >= 1.3 or office) and rng.random() < (0.85 if office else 0.6):
        parts.append(
            box(-0.25, 0.25, d / 2 - 0.12, d / 2 - 0.04, h + 0.1, h + 0.42, "television", "screen")
        )
        parts.append(box(-0.04, 0.04, d / 2 - 0.1, d / 2 - 0.06, h, h + 0.1, "television", "frame"))
    if office or rng.random() < 0.3:
        chair, gap = office_chair_parts(rng, 1), 0.42
    else:
        chair, gap = chair_parts(rng, 1), 0.36
    parts += moved(chair, _u(rng, -0.12, 0.12), -d / 2 - gap, math.pi + _u(rng, -0.35, 0.35))
    return make_group("desk", parts, "wall")


def bed_set(rng: Rng) -> Group:
    """A bed with headboard at the wall, pillows, and night stands with a lamp."""
    double = rng.random() < 0.7
    w, length = (_u(rng, 1.4, 1.8) if double else _u(rng, 0.9, 1.0)), _u(rng, 1.95, 2.1)
    base_h, mat_h = _u(rng, 0.25, 0.35), _u(rng, 0.18, 0.25)
    head_t, head_h = 0.06, _u(rng, 0.8, 1.1)
    y0, y1 = -length / 2, length / 2
    parts = [
        box(-w / 2, w / 2, y0, y1 - head_t, 0.0, base_h, "bed", "frame"),
        box(
            -w / 2 + 0.02,
            w / 2 - 0.02,
            y0 + 0.02,
            y1 - head_t,
            base_h,
            base_h + mat_h,
            "bed",
            "soft",
        ),
        box(-w / 2, w / 2, y1 - head_t, y1, 0.0, head_h, "bed", "frame"),
    ]
    top = base_h + mat_h
    n_pillows = 2 if double else 1
    pw = (w - 0.15) / n_pillows - 0.06
    for k in range(n_pillows):
        x = -w / 2 + 0.08 + k * (pw + 0.06)
        parts.append(
            box(
                x,
                x + pw,
                y1 - head_t - 0.42,
                y1 - head_t - 0.04,
                top,
                top + _u(rng, 0.1, 0.15),
                "pillow",
                "body",
                k,
            )
        )
    for k, sx in enumerate((-1, 1)):
        if rng.random() < 0.8:
            nw, nd, nh = _u(rng, 0.4, 0.5), _u(rng, 0.35, 0.42), _u(rng, 0.45, 0.6)
            x = sx * (w / 2 + 0.06 + nw / 2)
            parts.append(box(x - nw / 2, x + nw / 2, y1 - nd, y1, 0.0, nh, "night stand", "body"))
            if k == 0 or rng.random() < 0.4:
                parts += moved(lamp_parts(rng, floor=False, z0=nh, instance=k), x, y1 - nd / 2)
    return make_group("bed", parts, "wall")


def sofa_set(rng: Rng) -> Group:
    """A sofa with pillows, and often a coffee table on a rug in front of it."""
    w, d = _u(rng, 1.7, 2.4), _u(rng, 0.85, 0.95)
    seat_h, back_t, back_h, arm_w, arm_h = (
        _u(rng, 0.4, 0.45),
        0.2,
        _u(rng, 0.8, 0.9),
        0.15,
        _u(rng, 0.55, 0.65),
    )
    y0, y1 = -d / 2, d / 2
    parts = [
        box(-w / 2 + arm_w, w / 2 - arm_w, y0, y1 - back_t, 0.0, seat_h, "sofa", "body"),
        box(-w / 2, w / 2, y1 - back_t, y1, 0.0, back_h, "sofa", "body"),
        box(-w / 2, -w / 2 + arm_w, y0, y1 - back_t, 0.0, arm_h, "sofa", "body"),
        box(w / 2 - arm_w, w / 2, y0, y1 - back_t, 0.0, arm_h, "sofa", "body"),
    ]
    inner = w - 2 * arm_w
    n = int(rng.integers(1, 4))
    slots = np.linspace(-inner / 2, inner / 2, n + 2)[1:-1]
    for k, x in enumerate(slots):
        pw = min(_u(rng, 0.35, 0.45), inner / (n + 1) - 0.04)
        parts.append(
            box(
                x - pw / 2,
                x + pw / 2,
                y1 - back_t - 0.14,
                y1 - back_t,
                seat_h,
                seat_h + pw * 0.9,
                "pillow",
                "body",
                k,
            )
        )
    if rng.random() < 0.75:
        tw, td = _u(rng, 0.8, 1.2), _u(rng, 0.45, 0.6)
        ty = y0 - 0.4 - td / 2
        mat = 0.0
        if rng.random() < 0.7:
            mat = 0.008
            mw, md = tw + _u(rng, 0.6, 1.0), td + _u(rng, 0.5, 0.8)
            parts.append(
                box(
                    -mw / 2,
                    mw / 2,
                    ty - md / 2,
                    min(ty + md / 2, y0 - 0.02),
                    0.0,
                    mat,
                    "floor mat",
                    "body",
                )
            )
        parts += moved(table_parts(rng, tw, td, _u(rng, 0.38, 0.45)), 0.0, ty, dz=mat)
    return make_group("sofa", parts, "wall")


def bookshelf(rng: Rng) -> Group:
    """A bookshelf: sides and boards 1.8-2.5 cm thick, a thin back, runs of books."""
    w, d, h = _u(rng, 0.8, 1.3), _u(rng, 0.3, 0.38), _u(rng, 1.7, 2.05)
    t = _u(rng, 0.018, 0.025)
    y0, y1 = -d / 2, d / 2
    parts = [
        box(-w / 2, -w / 2 + t, y0, y1, 0.0, h, "bookshelf"),
        box(w / 2 - t, w / 2, y0, y1, 0.0, h, "bookshelf"),
        box(-w / 2 + t, w / 2 - t, y1 - 0.008, y1, 0.0, h, "bookshelf"),
    ]
    n_boards = int(rng.integers(4, 6))
    levels = np.linspace(0.06, h - t, n_boards + 1)
    gap = levels[1] - levels[0]
    for k, z in enumerate(levels):
        parts.append(box(-w / 2 + t, w / 2 - t, y0, y1 - 0.008, z, z + t, "bookshelf"))
        if k < n_boards and rng.random() < 0.9:
            parts += book_rows(
                rng,
                -w / 2 + t + 0.01,
                w / 2 - t - 0.01,
                y1 - 0.008 - 0.25,
                y1 - 0.009,
                z + t,
                gap - t - 0.03,
                k,
            )
    parts.append(box(-w / 2 + t, w / 2 - t, y0, y1 - 0.008, 0.0, 0.06, "bookshelf"))
    return make_group("bookshelf", parts, "wall")


def ladder_shelf(rng: Rng) -> Group:
    """A ladder shelf leaning against the wall (NYU40 "shelves"): two side rails 2.5-3.5 cm
    tilted 8-14 degrees and four or five boards 1.5-2 cm thick, shallower towards the top,
    open at the back and sides, with a few boxes or books on them."""
    w, h, lean = _u(rng, 0.6, 0.9), _u(rng, 1.6, 1.9), math.radians(_u(rng, 8.0, 14.0))
    rail, t = _u(rng, 0.025, 0.035), _u(rng, 0.015, 0.02)
    depth0 = _u(rng, 0.3, 0.4)
    half_len = (h - rail * math.sin(lean)) / (2 * math.cos(lean))  # square ends stay in [0, h]
    y_foot = -h * math.tan(lean)  # the feet stand forward; the tops rest on the wall at y = 0
    parts = []
    for sx in (-1, 1):
        x = sx * (w / 2 - rail / 2)
        parts.append(
            slab(
                (x, y_foot / 2 - rail / 2, h / 2),
                (rail / 2, rail / 2, half_len),
                lean,
                "shelves",
                "frame",
            )
        )
    n = int(rng.integers(4, 6))
    for k in range(n):
        z = 0.15 + k * (h - 0.35) / (n - 1)
        y_rail = y_foot * (1 - z / h) - rail / 2
        dep = depth0 * (1 - 0.6 * k / max(1, n - 1))
        parts.append(
            box(-w / 2 + rail, w / 2 - rail, y_rail - dep, y_rail + rail / 2, z, z + t, "shelves")
        )
        if rng.random() < 0.5:
            parts += book_rows(
                rng,
                -w / 2 + rail + 0.01,
                w / 2 - rail - 0.01,
                y_rail - dep + 0.01,
                y_rail,
                z + t,
                0.25,
                k,
            )
    return make_group("ladder_shelf", parts, "wall")


def cabinet_tv(rng: Rng) -> Group:
    """A low cabinet, often with a television on it."""
    w, d, h = _u(rng, 0.9, 1.7), _u(rng, 0.4, 0.5), _u(rng, 0.45, 0.75)
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, 0.0, h, "cabinet")]
    if rng.random() < 0.8:
        tw = min(w - 0.1, _u(rng, 0.8, 1.3))
        th = tw * 0.58
        parts.append(box(-0.12, 0.12, -0.1, 0.1, h, h + 0.04, "television", "frame"))
        parts.append(box(-0.03, 0.03, -0.03, 0.03, h + 0.04, h + 0.1, "television", "frame"))
        parts.append(
            box(-tw / 2, tw / 2, -0.03, 0.03, h + 0.1, h + 0.1 + th, "television", "screen")
        )
    elif rng.random() < 0.7:
        parts += cardboard_boxes(
            rng, -w / 2 + 0.05, w / 2 - 0.05, -d / 2 + 0.05, d / 2 - 0.05, h, 0.35
        )
    return make_group("cabinet", parts, "wall")


def tall_cabinet(rng: Rng) -> Group:
    """A tall storage cabinet (wardrobe, office cupboard)."""
    w, d, h = _u(rng, 0.8, 1.2), _u(rng, 0.45, 0.6), _u(rng, 1.4, 2.0)
    return make_group(
        "tall_cabinet", [box(-w / 2, w / 2, -d / 2, d / 2, 0.0, h, "cabinet")], "wall"
    )


def dresser(rng: Rng) -> Group:
    """A chest of drawers, sometimes with a box or a lamp on top."""
    w, d, h = _u(rng, 0.9, 1.4), _u(rng, 0.45, 0.55), _u(rng, 0.75, 1.05)
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, 0.0, h, "dresser")]
    if rng.random() < 0.5:
        parts += moved(lamp_parts(rng, floor=False, z0=h), w / 2 - 0.2, 0.0)
    return make_group("dresser", parts, "wall")


def kitchen(rng: Rng) -> Group:
    """Base cabinets under a counter top, wall cabinets above and a refrigerator beside."""
    w, d = _u(rng, 1.8, 3.0), 0.6
    h, t = 0.86, 0.04
    parts = [
        box(-w / 2, w / 2, -d / 2 + 0.05, d / 2, 0.0, h, "cabinet"),
        box(-w / 2, w / 2, -d / 2, d / 2, h, h + t, "counter", "top"),
    ]
    if rng.random() < 0.8:
        parts.append(
            box(
                -w / 2,
                w / 2,
                d / 2 - 0.35,
                d / 2,
                _u(rng, 1.45, 1.55),
                _u(rng, 2.0, 2.1),
                "cabinet",
                "body",
                1,
            )
        )
    if rng.random() < 0.85:
        fw, fh = _u(rng, 0.6, 0.75), _u(rng, 1.7, 1.9)
        side = rng.choice([-1, 1])
        x = side * (w / 2 + 0.04 + fw / 2)
        parts.append(box(x - fw / 2, x + fw / 2, d / 2 - 0.68, d / 2, 0.0, fh, "refrigerator"))
    return make_group("kitchen", parts, "wall")


def shelving(rng: Rng) -> Group:
    """A metal shelving unit: four round posts 2-2.5 cm across, boards 1.8-2.5 cm thick
    and boxes on them."""
    w, d, h = _u(rng, 0.9, 1.8), _u(rng, 0.4, 0.6), _u(rng, 1.5, 2.0)
    r, t = _u(rng, 0.01, 0.0125), _u(rng, 0.018, 0.025)
    parts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - r), sy * (d / 2 - r)
            parts.append(rod((x, y, r), (x, y, h - r), r, "shelves", "frame"))
    n = int(rng.integers(3, 5))
    levels = np.linspace(0.1, h - t, n + 1)
    for k, z in enumerate(levels):
        parts.append(box(-w / 2 + 2 * r, w / 2 - 2 * r, -d / 2, d / 2, z, z + t, "shelves"))
        if k < n:
            parts += cardboard_boxes(
                rng,
                -w / 2 + 2 * r + 0.02,
                w / 2 - 2 * r - 0.02,
                -d / 2 + 0.03,
                d / 2 - 0.03,
                z + t,
                levels[1] - levels[0] - t - 0.04,
                10 * k,
            )
    return make_group("shelving", parts, "wall")


def box_pile(rng: Rng) -> Group:
    """One to four boxes on the floor, some stacked, free-standing."""
    parts = []
    n = int(rng.integers(1, 4))
    x = 0.0
    for k in range(n):
        w, d, h = _u(rng, 0.35, 0.6), _u(rng, 0.3, 0.5), _u(rng, 0.25, 0.5)
        parts.append(box(x, x + w, -d / 2, d / 2, 0.0, h, "box", "body", 2 * k))
        if rng.random() < 0.4:
            w2, d2 = w * _u(rng, 0.6, 0.95), d * _u(rng, 0.6, 0.95)
            parts.append(
                box(
                    x + 0.01,
                    x + 0.01 + w2,
                    -d2 / 2,
                    d2 / 2,
                    h,
                    h + _u(rng, 0.2, 0.35),
                    "box",
                    "body",
                    2 * k + 1,
                )
            )
        x += w + _u(rng, 0.02, 0.08)
    return make_group("boxes", parts, "free")


def floor_lamp(rng: Rng) -> Group:
    return make_group("floor_lamp", lamp_parts(rng, floor=True), "free")


def door(rng: Rng) -> Group:
    """A door leaf in a frame on a wall, with a handle; keeps the floor in front clear."""
    w, h = _u(rng, 0.8, 0.95), _u(rng, 2.0, 2.1)
    f, t = 0.06, 0.04
    y1 = 0.0
    parts = [
        box(-w / 2 - f, -w / 2, y1 - t - 0.01, y1, 0.0, h + f, "door", "frame"),
        box(w / 2, w / 2 + f, y1 - t - 0.01, y1, 0.0, h + f, "door", "frame"),
        box(-w / 2, w / 2, y1 - t - 0.01, y1, h, h + f, "door", "frame"),
        box(-w / 2, w / 2, y1 - t, y1, 0.005, h, "door", "body"),
    ]
    hx = (w / 2 - 0.1) * rng.choice([-1, 1])
    parts.append(box(hx - 0.06, hx + 0.06, y1 - t - 0.06, y1 - t, 0.98, 1.02, "door", "frame"))
    keepout = ((-w / 2 - f, y1 - 0.9, 0.0), (w / 2 + f, y1, h + f))
    return make_group("door", parts, "onwall", keepout)


def window(rng: Rng, dressing: str) -> Group:
    """A glazed window on a wall; ``dressing`` is "curtains", "blinds" or "none"."""
    w, h, sill = _u(rng, 0.9, 2.0), _u(rng, 1.0, 1.4), _u(rng, 0.7, 0.9)
    f, t = 0.05, 0.05
    top = sill + h
    parts = [
        box(-w / 2, w / 2, -t, 0.0, sill, sill + f, "window", "frame"),
        box(-w / 2, w / 2, -t, 0.0, top - f, top, "window", "frame"),
        box(-w / 2, -w / 2 + f, -t, 0.0, sill + f, top - f, "window", "frame"),
        box(w / 2 - f, w / 2, -t, 0.0, sill + f, top - f, "window", "frame"),
        box(-w / 2 + f, w / 2 - f, -0.02, 0.0, sill + f, top - f, "window", "glass"),
        box(-w / 2 - 0.05, w / 2 + 0.05, -t - 0.06, -t, sill - 0.03, sill, "window", "frame"),
    ]
    if w > 1.3:
        parts.append(box(-0.025, 0.025, -t, -0.02, sill + f, top - f, "window", "frame"))
    if dressing == "curtains":
        cw = _u(rng, 0.3, 0.5)
        for k, sx in enumerate((-1, 1)):
            x0 = w / 2 - cw * 0.3 if sx > 0 else -w / 2 - cw * 0.7
            parts.append(
                box(x0, x0 + cw, -t - 0.2, -t - 0.08, 0.02, top + 0.15, "curtain", "body", k)
            )
    elif dressing == "blinds":
        bh = h * _u(rng, 0.25, 0.7)
        parts.append(
            box(-w / 2 + f, w / 2 - f, -t - 0.04, -t - 0.01, top - f - bh, top - f, "blinds")
        )
    return make_group("window", parts, "onwall")


def picture(rng: Rng) -> Group:
    """A framed picture hung at eye height."""
    w, h = _u(rng, 0.3, 1.0), _u(rng, 0.3, 0.8)
    zc = _u(rng, 1.35, 1.7)
    f = 0.03
    parts = [
        box(-w / 2, w / 2, -0.03, 0.0, zc - h / 2, zc + h / 2, "picture", "frame"),
        box(
            -w / 2 + f,
            w / 2 - f,
            -0.035,
            -0.03,
            zc - h / 2 + f,
            zc + h / 2 - f,
            "picture",
            "canvas",
        ),
    ]
    return make_group("picture", parts, "onwall")


def whiteboard(rng: Rng) -> Group:
    w, h = _u(rng, 1.2, 2.0), _u(rng, 0.9, 1.2)
    z0 = _u(rng, 0.85, 1.0)
    parts = [
        box(-w / 2, w / 2, -0.02, 0.0, z0, z0 + h, "whiteboard", "frame"),
        box(-w / 2 + 0.02, w / 2 - 0.02, -0.025, -0.02, z0 + 0.02, z0 + h - 0.02, "whiteboard"),
        box(-w / 2 + 0.1, w / 2 - 0.1, -0.08, -0.02, z0 - 0.03, z0, "whiteboard", "frame"),
    ]
    return make_group("whiteboard", parts, "onwall")


def wall_tv(rng: Rng) -> Group:
    w = _u(rng, 1.0, 1.6)
    zc = _u(rng, 1.4, 1.6)
    parts = [
        box(-w / 2, w / 2, -0.06, -0.02, zc - w * 0.29, zc + w * 0.29, "television", "screen"),
        box(-0.2, 0.2, -0.02, 0.0, zc - 0.15, zc + 0.15, "television", "frame"),
    ]
    return make_group("wall_tv", parts, "onwall")


def mirror(rng: Rng) -> Group:
    w, h = _u(rng, 0.4, 0.8), _u(rng, 0.6, 1.2)
    z0 = _u(rng, 0.9, 1.1)
    parts = [
        box(-w / 2, w / 2, -0.025, 0.0, z0, z0 + h, "mirror", "frame"),
        box(
            -w / 2 + 0.03, w / 2 - 0.03, -0.03, -0.025, z0 + 0.03, z0 + h - 0.03, "mirror", "glass"
        ),
    ]
    return make_group("mirror", parts, "onwall")


# A group that finds no place is tried once more in this more compact form.
FALLBACKS: dict[str, Callable[[Rng], Group]] = {"dining": dining_by_wall}

BUILDERS: dict[str, Callable[[Rng], Group]] = {
    "dining": dining_set,
    "meeting": meeting_set,
    "chairs": loose_chairs,
    "stools": stool_row,
    "desk": desk_set,
    "office_desk": lambda rng: desk_set(rng, office=True),
    "ladder_shelf": ladder_shelf,
    "arc_lamp": arc_lamp,
    "plant": plant,
    "bed": bed_set,
    "sofa": sofa_set,
    "bookshelf": bookshelf,
    "cabinet": cabinet_tv,
    "tall_cabinet": tall_cabinet,
    "dresser": dresser,
    "kitchen": kitchen,
    "shelving": shelving,
    "boxes": box_pile,
    "floor_lamp": floor_lamp,
    "door": door,
    "window_curtains": lambda rng: window(rng, "curtains"),
    "window_blinds": lambda rng: window(rng, "blinds"),
    "window": lambda rng: window(rng, "none"),
    "picture": picture,
    "whiteboard": whiteboard,
    "wall_tv": wall_tv,
    "mirror": mirror,
}
