"""Point lights, Lambertian irradiance and shadow rays.

Shading depends only on the surface point, its normal and the lights, never on the
camera, so a surface has the same radiance in every view (before per-frame exposure).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csa_core.data.synth.families import RoomFamily
from csa_core.data.synth.layout import Room
from csa_core.data.synth.solids import Solids


@dataclass(frozen=True)
class Light:
    """A point light: position (3,), linear RGB power (3,), whether it casts shadows."""

    position: np.ndarray
    power: np.ndarray
    shadows: bool


def _push_out(
    pos: np.ndarray, room: Room, blockers: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """Move a light towards the room centre until it is outside every blocker's bounds."""
    centre = np.array([room.width / 2, room.depth / 2, pos[2]])
    for k in range(21):
        p = pos + (centre - pos) * (k / 20)
        if not any(np.all(p > lo - 0.05) and np.all(p < hi + 0.05) for lo, hi in blockers):
            return p
    return centre


def place_lights(family: RoomFamily, room: Room, rng: np.random.Generator) -> list[Light]:
    """Lights of a family in a room: ceiling lights, or a window key light plus a ceiling fill."""
    style = family.lighting
    color = np.asarray(style.color) * np.exp(rng.normal(0.0, style.color_jitter, 3))
    blockers = [g.aabb() for g in room.groups]
    lights: list[Light] = []
    z = room.height - 0.25
    windows = [g for g in room.groups if g.group.kind == "window"]
    if style.placement == "window" and windows:
        win = windows[int(rng.integers(len(windows)))]
        lo, hi = win.aabb()
        inward = np.array([[0, 1], [-1, 0], [0, -1], [1, 0]][win.wall], dtype=np.float64)
        top = max(p.center[2] + p.half[2] for p in win.group.parts if p.label == "window")
        pos = np.array(
            [
                (lo[0] + hi[0]) / 2 + 0.6 * inward[0],
                (lo[1] + hi[1]) / 2 + 0.6 * inward[1],
                min(top + 0.2, z),
            ]
        )
        lights.append(
            Light(
                _push_out(pos, room, blockers),
                color * rng.uniform(*style.intensity),
                style.shadow_lights > 0,
            )
        )
        fill = np.array([room.width / 2, room.depth / 2, z])
        lights.append(
            Light(
                _push_out(fill, room, blockers),
                np.asarray(style.fill_color) * style.fill_intensity,
                False,
            )
        )
        return lights
    n = int(rng.integers(style.count[0], style.count[1] + 1))
    long_x = room.width >= room.depth
    length = room.width if long_x else room.depth
    for k in range(n):
        a = (k + 0.5) / n * length + rng.uniform(-0.25, 0.25)
        b = (room.depth if long_x else room.width) / 2 + rng.uniform(-0.4, 0.4)
        pos = np.array([a, b, z]) if long_x else np.array([b, a, z])
        power = color * rng.uniform(*style.intensity) / np.sqrt(n)
        lights.append(Light(_push_out(pos, room, blockers), power, k < style.shadow_lights))
    return lights


def irradiance(
    points: np.ndarray,
    normals: np.ndarray,
    lights: list[Light],
    ambient: np.ndarray,
    falloff_m: float,
    casters: Solids,
    caster_bounds: tuple[np.ndarray, np.ndarray],
    chunks: list[np.ndarray],
) -> np.ndarray:
    """Irradiance (n, 3) at surface points: ambient plus Lambert terms of the lights.

    Shadow rays run from each light to the points, chunk by chunk (spatially coherent
    groups of points, e.g. image tiles); a chunk only tests casters whose bounds meet the
    bounds of the chunk's points and the light, which keeps it all-rays x all-boxes but small.
    """
    e = np.broadcast_to(np.asarray(ambient, dtype=np.float64), points.shape).copy()
    c_lo, c_hi = caster_bounds
    for light in lights:
        to_light = light.position - points
        dist = np.linalg.norm(to_light, axis=1)
        cos = np.einsum("ij,ij->i", normals, to_light) / np.maximum(dist, 1e-9)
        lit = cos > 0
        if light.shadows and len(casters):
            for idx in chunks:
                sel = idx[lit[idx]]
                if len(sel) == 0:
                    continue
                pts = points[sel]
                lo = np.minimum(pts.min(axis=0), light.position)
                hi = np.maximum(pts.max(axis=0), light.position)
                cand = np.nonzero(np.all(c_lo < hi, axis=1) & np.all(c_hi > lo, axis=1))[0]
                if len(cand) == 0:
                    continue
                # Stop 5 mm short of the point so its own surface does not shadow it.
                t_end = 1.0 - 0.005 / np.maximum(dist[sel], 1e-6)
                blocked = casters.subset(cand).any_hit(
                    light.position, pts - light.position, t_end, eps=1e-3
                )
                lit[sel[blocked]] = False
        gain = np.where(lit, cos, 0.0) / (1.0 + (dist / falloff_m) ** 2)
        e += gain[:, None] * light.power[None, :]
    return e
