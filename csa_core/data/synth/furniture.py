"""Furniture made of boxes, each builder returning a group in its own frame.

Group frame: metres, z up, floor at z = 0, the footprint centred on the origin, the front
facing -y and the back (the side that goes against a wall) at +y. Every part carries its
NYU40 class name and a material role ("body", "top", "frame", "soft", "screen", "glass",
"shade", "canvas"); the family decides what each (class, role) looks like. Builders keep
parts of different objects apart by construction, so groups never interpenetrate
internally; the layout keeps groups apart from each other.
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
    """One box of a group: centre and half-extents in the group frame, yaw about +z."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    label: str
    role: str = "body"
    yaw: float = 0.0
    instance: int = 0  # parts of one group with the same (label, role, instance) share a material


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


def box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, label: str, role: str = "body", instance: int = 0) -> Part:
    """A part from its extents along x, y and z."""
    return Part(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2), ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2), label, role, 0.0, instance)


def _parts_bounds(parts: tuple[Part, ...] | list[Part]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for p in parts:
        c, s = abs(math.cos(p.yaw)), abs(math.sin(p.yaw))
        ext = np.array([c * p.half[0] + s * p.half[1], s * p.half[0] + c * p.half[1], p.half[2]])
        lo = np.minimum(lo, np.asarray(p.center) - ext)
        hi = np.maximum(hi, np.asarray(p.center) + ext)
    return lo, hi


def moved(parts: list[Part] | tuple[Part, ...], dx: float, dy: float, yaw: float = 0.0, dz: float = 0.0, instance: int | None = None) -> list[Part]:
    """Parts rotated by ``yaw`` about the origin, then shifted by (dx, dy, dz)."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for p in parts:
        x, y, z = p.center
        inst = p.instance if instance is None else instance
        out.append(replace(p, center=(c * x - s * y + dx, s * x + c * y + dy, z + dz), yaw=p.yaw + yaw, instance=inst))
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


def table_parts(rng: Rng, w: float, d: float, h: float, instance: int = 0) -> list[Part]:
    """A table top on four legs."""
    top, leg, inset = 0.04, _u(rng, 0.04, 0.07), 0.05
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, h - top, h, "table", "top", instance)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x = sx * (w / 2 - inset - leg / 2)
            y = sy * (d / 2 - inset - leg / 2)
            parts.append(box(x - leg / 2, x + leg / 2, y - leg / 2, y + leg / 2, 0.0, h - top, "table", "frame", instance))
    return parts


def chair_parts(rng: Rng, instance: int = 0) -> list[Part]:
    """Seat, backrest at +y and four legs; about 0.45 m wide."""
    w, d = _u(rng, 0.42, 0.50), _u(rng, 0.42, 0.48)
    seat_h, seat_t = _u(rng, 0.44, 0.48), 0.05
    back_h, back_t, leg = _u(rng, 0.35, 0.5), 0.04, 0.035
    parts = [
        box(-w / 2, w / 2, -d / 2, d / 2, seat_h - seat_t, seat_h, "chair", "body", instance),
        box(-w / 2, w / 2, d / 2 - back_t, d / 2, seat_h, seat_h + back_h, "chair", "body", instance),
    ]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - leg / 2 - 0.01), sy * (d / 2 - leg / 2 - 0.01)
            parts.append(box(x - leg / 2, x + leg / 2, y - leg / 2, y + leg / 2, 0.0, seat_h - seat_t, "chair", "frame", instance))
    return parts


def lamp_parts(rng: Rng, floor: bool, z0: float = 0.0, instance: int = 0) -> list[Part]:
    """A lamp: base, pole and shade; a floor lamp or a small table lamp standing at ``z0``."""
    if floor:
        base, pole_h, shade_w, shade_h = _u(rng, 0.25, 0.35), _u(rng, 1.2, 1.5), _u(rng, 0.3, 0.45), _u(rng, 0.25, 0.35)
    else:
        base, pole_h, shade_w, shade_h = _u(rng, 0.1, 0.15), _u(rng, 0.2, 0.3), _u(rng, 0.18, 0.25), _u(rng, 0.14, 0.2)
    pole = 0.025 if floor else 0.02
    return [
        box(-base / 2, base / 2, -base / 2, base / 2, z0, z0 + 0.03, "lamp", "frame", instance),
        box(-pole / 2, pole / 2, -pole / 2, pole / 2, z0 + 0.03, z0 + 0.03 + pole_h, "lamp", "frame", instance),
        box(-shade_w / 2, shade_w / 2, -shade_w / 2, shade_w / 2, z0 + 0.03 + pole_h, z0 + 0.03 + pole_h + shade_h, "lamp", "shade", instance),
    ]


def book_rows(rng: Rng, x0: float, x1: float, y0: float, y1: float, z0: float, max_h: float, instance: int = 0) -> list[Part]:
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
        parts.append(box(a, b, y0, y0 + min(y1 - y0, _u(rng, 0.15, 0.24)), z0, z0 + h, "books", "body", instance))
    return parts


def cardboard_boxes(rng: Rng, x0: float, x1: float, y0: float, y1: float, z0: float, max_h: float, instance: int = 0) -> list[Part]:
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
    """A table with chairs around it facing it, free-standing."""
    w, d = _u(rng, 1.0, 1.8), _u(rng, 0.75, 1.0)
    parts = table_parts(rng, w, d, _u(rng, 0.72, 0.77))
    per_side = 2 if w > 1.35 else 1
    inst = 1
    for side in (-1, 1):
        xs = np.linspace(-w / 4, w / 4, per_side) if per_side == 2 else [0.0]
        for x in xs:
            if rng.random() < 0.85:
                chair = chair_parts(rng, inst)
                yaw = (0.0 if side > 0 else math.pi) + _u(rng, -0.2, 0.2)
                parts += moved(chair, float(x), side * (d / 2 + 0.36), yaw)
                inst += 1
    if rng.random() < 0.5:
        parts += moved(chair_parts(rng, inst), -(w / 2 + 0.36), 0.0, math.pi / 2 + _u(rng, -0.2, 0.2))
    return make_group("dining", parts, "free")


def desk_set(rng: Rng) -> Group:
    """A desk against a wall, its chair in front, a lamp, books or a box on top."""
    w, d, h = _u(rng, 1.1, 1.6), _u(rng, 0.6, 0.75), _u(rng, 0.72, 0.76)
    t, side = 0.03, 0.03
    parts = [
        box(-w / 2, w / 2, -d / 2, d / 2, h - t, h, "desk", "top"),
        box(-w / 2, -w / 2 + side, -d / 2 + 0.02, d / 2, 0.0, h - t, "desk", "body"),
        box(w / 2 - side, w / 2, -d / 2 + 0.02, d / 2, 0.0, h - t, "desk", "body"),
    ]
    if rng.random() < 0.6:
        dw = _u(rng, 0.35, 0.45)
        parts.append(box(w / 2 - side - dw, w / 2 - side - 0.005, -d / 2 + 0.03, d / 2, h - t - 0.45, h - t, "desk", "body"))
    side_sign = float(rng.choice([-1, 1]))
    if rng.random() < 0.7:
        parts += moved(lamp_parts(rng, floor=False, z0=h), side_sign * (w / 2 - 0.15), d / 2 - 0.15)
    if rng.random() < 0.7:
        edge = -side_sign * (w / 2 - 0.03)
        parts += book_rows(rng, min(edge, edge + 0.3 * side_sign), max(edge, edge + 0.3 * side_sign), d / 2 - 0.28, d / 2 - 0.02, h, 0.3)
    if w >= 1.3 and rng.random() < 0.6:
        parts.append(box(-0.25, 0.25, d / 2 - 0.12, d / 2 - 0.04, h + 0.1, h + 0.42, "television", "screen"))
        parts.append(box(-0.04, 0.04, d / 2 - 0.1, d / 2 - 0.06, h, h + 0.1, "television", "frame"))
    chair = chair_parts(rng, 1)
    parts += moved(chair, _u(rng, -0.15, 0.15), -d / 2 - 0.33, math.pi + _u(rng, -0.35, 0.35))
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
        box(-w / 2 + 0.02, w / 2 - 0.02, y0 + 0.02, y1 - head_t, base_h, base_h + mat_h, "bed", "soft"),
        box(-w / 2, w / 2, y1 - head_t, y1, 0.0, head_h, "bed", "frame"),
    ]
    top = base_h + mat_h
    n_pillows = 2 if double else 1
    pw = (w - 0.15) / n_pillows - 0.06
    for k in range(n_pillows):
        x = -w / 2 + 0.08 + k * (pw + 0.06)
        parts.append(box(x, x + pw, y1 - head_t - 0.42, y1 - head_t - 0.04, top, top + _u(rng, 0.1, 0.15), "pillow", "body", k))
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
    seat_h, back_t, back_h, arm_w, arm_h = _u(rng, 0.4, 0.45), 0.2, _u(rng, 0.8, 0.9), 0.15, _u(rng, 0.55, 0.65)
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
        parts.append(box(x - pw / 2, x + pw / 2, y1 - back_t - 0.14, y1 - back_t, seat_h, seat_h + pw * 0.9, "pillow", "body", k))
    if rng.random() < 0.75:
        tw, td = _u(rng, 0.8, 1.2), _u(rng, 0.45, 0.6)
        ty = y0 - 0.4 - td / 2
        mat = 0.0
        if rng.random() < 0.7:
            mat = 0.008
            mw, md = tw + _u(rng, 0.6, 1.0), td + _u(rng, 0.5, 0.8)
            parts.append(box(-mw / 2, mw / 2, ty - md / 2, min(ty + md / 2, y0 - 0.02), 0.0, mat, "floor mat", "body"))
        parts += moved(table_parts(rng, tw, td, _u(rng, 0.38, 0.45)), 0.0, ty, dz=mat)
    return make_group("sofa", parts, "wall")


def bookshelf(rng: Rng) -> Group:
    """A bookshelf: sides, back, boards and runs of books on each board."""
    w, d, h = _u(rng, 0.8, 1.3), _u(rng, 0.3, 0.38), _u(rng, 1.7, 2.05)
    t = 0.025
    y0, y1 = -d / 2, d / 2
    parts = [
        box(-w / 2, -w / 2 + t, y0, y1, 0.0, h, "bookshelf"),
        box(w / 2 - t, w / 2, y0, y1, 0.0, h, "bookshelf"),
        box(-w / 2 + t, w / 2 - t, y1 - 0.012, y1, 0.0, h, "bookshelf"),
    ]
    n_boards = int(rng.integers(4, 6))
    levels = np.linspace(0.06, h - t, n_boards + 1)
    gap = levels[1] - levels[0]
    for k, z in enumerate(levels):
        parts.append(box(-w / 2 + t, w / 2 - t, y0, y1 - 0.012, z, z + t, "bookshelf"))
        if k < n_boards and rng.random() < 0.9:
            parts += book_rows(rng, -w / 2 + t + 0.01, w / 2 - t - 0.01, y1 - 0.012 - 0.25, y1 - 0.013, z + t, gap - t - 0.03, k)
    parts.append(box(-w / 2 + t, w / 2 - t, y0, y1 - 0.012, 0.0, 0.06, "bookshelf"))
    return make_group("bookshelf", parts, "wall")


def cabinet_tv(rng: Rng) -> Group:
    """A low cabinet, often with a television on it."""
    w, d, h = _u(rng, 0.9, 1.7), _u(rng, 0.4, 0.5), _u(rng, 0.45, 0.75)
    parts = [box(-w / 2, w / 2, -d / 2, d / 2, 0.0, h, "cabinet")]
    if rng.random() < 0.8:
        tw = min(w - 0.1, _u(rng, 0.8, 1.3))
        th = tw * 0.58
        parts.append(box(-0.12, 0.12, -0.1, 0.1, h, h + 0.04, "television", "frame"))
        parts.append(box(-0.03, 0.03, -0.03, 0.03, h + 0.04, h + 0.1, "television", "frame"))
        parts.append(box(-tw / 2, tw / 2, -0.03, 0.03, h + 0.1, h + 0.1 + th, "television", "screen"))
    elif rng.random() < 0.7:
        parts += cardboard_boxes(rng, -w / 2 + 0.05, w / 2 - 0.05, -d / 2 + 0.05, d / 2 - 0.05, h, 0.35)
    return make_group("cabinet", parts, "wall")


def tall_cabinet(rng: Rng) -> Group:
    """A tall storage cabinet (wardrobe, office cupboard)."""
    w, d, h = _u(rng, 0.8, 1.2), _u(rng, 0.45, 0.6), _u(rng, 1.4, 2.0)
    return make_group("tall_cabinet", [box(-w / 2, w / 2, -d / 2, d / 2, 0.0, h, "cabinet")], "wall")


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
        parts.append(box(-w / 2, w / 2, d / 2 - 0.35, d / 2, _u(rng, 1.45, 1.55), _u(rng, 2.0, 2.1), "cabinet", "body", 1))
    if rng.random() < 0.85:
        fw, fh = _u(rng, 0.6, 0.75), _u(rng, 1.7, 1.9)
        side = rng.choice([-1, 1])
        x = side * (w / 2 + 0.04 + fw / 2)
        parts.append(box(x - fw / 2, x + fw / 2, d / 2 - 0.68, d / 2, 0.0, fh, "refrigerator"))
    return make_group("kitchen", parts, "wall")


def shelving(rng: Rng) -> Group:
    """A metal shelving unit: four posts, boards and boxes on them."""
    w, d, h = _u(rng, 0.9, 1.8), _u(rng, 0.4, 0.6), _u(rng, 1.5, 2.0)
    post, t = 0.04, 0.02
    parts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - post / 2), sy * (d / 2 - post / 2)
            parts.append(box(x - post / 2, x + post / 2, y - post / 2, y + post / 2, 0.0, h, "shelves", "frame"))
    n = int(rng.integers(3, 5))
    levels = np.linspace(0.1, h - t, n + 1)
    for k, z in enumerate(levels):
        parts.append(box(-w / 2 + post, w / 2 - post, -d / 2, d / 2, z, z + t, "shelves"))
        if k < n:
            parts += cardboard_boxes(rng, -w / 2 + post + 0.02, w / 2 - post - 0.02, -d / 2 + 0.03, d / 2 - 0.03, z + t, levels[1] - levels[0] - t - 0.04, 10 * k)
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
            parts.append(box(x + 0.01, x + 0.01 + w2, -d2 / 2, d2 / 2, h, h + _u(rng, 0.2, 0.35), "box", "body", 2 * k + 1))
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
            parts.append(box(x0, x0 + cw, -t - 0.2, -t - 0.08, 0.02, top + 0.15, "curtain", "body", k))
    elif dressing == "blinds":
        bh = h * _u(rng, 0.25, 0.7)
        parts.append(box(-w / 2 + f, w / 2 - f, -t - 0.04, -t - 0.01, top - f - bh, top - f, "blinds"))
    return make_group("window", parts, "onwall")


def picture(rng: Rng) -> Group:
    """A framed picture hung at eye height."""
    w, h = _u(rng, 0.3, 1.0), _u(rng, 0.3, 0.8)
    zc = _u(rng, 1.35, 1.7)
    f = 0.03
    parts = [
        box(-w / 2, w / 2, -0.03, 0.0, zc - h / 2, zc + h / 2, "picture", "frame"),
        box(-w / 2 + f, w / 2 - f, -0.035, -0.03, zc - h / 2 + f, zc + h / 2 - f, "picture", "canvas"),
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
        box(-w / 2 + 0.03, w / 2 - 0.03, -0.03, -0.025, z0 + 0.03, z0 + h - 0.03, "mirror", "glass"),
    ]
    return make_group("mirror", parts, "onwall")


BUILDERS: dict[str, Callable[[Rng], Group]] = {
    "dining": dining_set,
    "desk": desk_set,
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
