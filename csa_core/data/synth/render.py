"""Render colour, z-depth and NYU40 labels of a room from a posed pinhole camera.

Depth and labels come from the ray through each pixel centre. Primary rays are cast tile
by tile: a tile only tests the solids (boxes and capsules) whose projected bounds touch it
(exact culling: a solid's image lies inside the bounds of the projected corners of its box
or bounding box when all are in front of the camera), so each tile is one all-rays x
all-candidate-solids test.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from csa_core.data.camera import Intrinsics, pixel_rays
from csa_core.data.nyu40 import class_id
from csa_core.data.synth.boxes import BoxSet, interior_exit
from csa_core.data.synth.families import RoomFamily
from csa_core.data.synth.furniture import Part
from csa_core.data.synth.layout import Room
from csa_core.data.synth.lighting import Light, irradiance
from csa_core.data.synth.solids import CapsuleSet, Solids
from csa_core.data.synth.textures import SHELL_CLASSES, MaterialTable, albedo, find_look

TILE_PX = 40
NEAR_M = 0.02
WALL, FLOOR, CEILING = class_id("wall"), class_id("floor"), class_id("ceiling")


@dataclass
class RoomModel:
    """Everything needed to render a room: solids with class ids and materials, the shell
    (interior box) materials, the material table and the lights."""

    lo: np.ndarray
    hi: np.ndarray
    solids: Solids
    labels: np.ndarray  # (n,) uint8 NYU40 ids
    material: np.ndarray  # (n,) material ids
    casts_shadow: np.ndarray  # (n,) bool
    shell_material: tuple[int, int, int]  # wall, floor, ceiling
    materials: dict[str, np.ndarray]
    lights: list[Light]
    ambient: np.ndarray
    falloff_m: float


def room_solids(room: Room) -> tuple[Solids, list[tuple[int, Part]]]:
    """A room's furniture as solids, and the (group index, part) of each solid in order."""
    boxes: list[tuple[np.ndarray, np.ndarray, float, float]] = []
    caps: list[tuple[np.ndarray, np.ndarray, float]] = []
    box_src: list[tuple[int, Part]] = []
    cap_src: list[tuple[int, Part]] = []
    for gi, g in enumerate(room.groups):
        for centre, half, yaw, part in g.world_parts():
            if part.shape == "rod":
                axis = replace(part, yaw=yaw).rotation()[:, 2] * half[2]
                caps.append((centre - axis, centre + axis, float(half[0])))
                cap_src.append((gi, part))
            else:
                boxes.append((centre, half, yaw, part.tilt))
                box_src.append((gi, part))
    box_set = BoxSet(
        np.array([b[0] for b in boxes]).reshape(-1, 3),
        np.array([b[1] for b in boxes]).reshape(-1, 3),
        np.array([b[2] for b in boxes], dtype=np.float64),
        np.array([b[3] for b in boxes], dtype=np.float64),
    )
    cap_set = CapsuleSet(
        np.array([c[0] for c in caps]).reshape(-1, 3),
        np.array([c[1] for c in caps]).reshape(-1, 3),
        np.array([c[2] for c in caps], dtype=np.float64),
    )
    return Solids(box_set, cap_set), box_src + cap_src


def build_model(
    room: Room, family: RoomFamily, lights: list[Light], rng: np.random.Generator
) -> RoomModel:
    """The room's solids, and a material drawn for every (group, class, role, instance)."""
    table = MaterialTable.for_room(family.appearance, rng)
    shell = tuple(
        table.add(find_look(family, name, "body"), rng, shell=True) for name in SHELL_CLASSES
    )
    solids, sources = room_solids(room)
    keys: dict[tuple, int] = {}
    for gi, g in enumerate(room.groups):  # materials drawn in part order, whatever the shape
        for part in g.group.parts:
            key = (gi, part.label, part.role, part.instance)
            if key not in keys:
                keys[key] = table.add(find_look(family, part.label, part.role), rng)
    mats = [keys[(gi, p.label, p.role, p.instance)] for gi, p in sources]
    labels = [class_id(p.label) for _, p in sources]
    casts = [room.groups[gi].on_floor and p.label != "floor mat" for gi, p in sources]
    return RoomModel(
        lo=room.lo,
        hi=room.hi,
        solids=solids,
        labels=np.array(labels, dtype=np.uint8),
        material=np.asarray(mats, dtype=np.int64),
        casts_shadow=np.array(casts, dtype=bool),
        shell_material=shell,
        materials=table.arrays(),
        lights=lights,
        ambient=np.asarray(family.lighting.ambient, dtype=np.float64),
        falloff_m=family.lighting.falloff_m,
    )


class FrameRenderer:
    """Renders a :class:`RoomModel` at one camera resolution; reusable across poses."""

    def __init__(self, model: RoomModel, intr: Intrinsics):
        self.model = model
        self.intr = intr
        self.corners = model.solids.corners()
        self.casters = model.solids.subset(np.nonzero(model.casts_shadow)[0])
        self.caster_bounds = self.casters.aabb()
        self.tiles = self._tiles()

    def _tiles(self) -> list[tuple[int, int, int, int, np.ndarray]]:
        w, h = self.intr.width, self.intr.height
        nx, ny = max(1, round(w / TILE_PX)), max(1, round(h / TILE_PX))
        xs = np.linspace(0, w, nx + 1).astype(int)
        ys = np.linspace(0, h, ny + 1).astype(int)
        tiles = []
        for y0, y1 in zip(ys[:-1], ys[1:], strict=True):
            for x0, x1 in zip(xs[:-1], xs[1:], strict=True):
                idx = (np.arange(y0, y1)[:, None] * w + np.arange(x0, x1)[None, :]).ravel()
                tiles.append((x0, x1, y0, y1, idx))
        return tiles

    def _projected_bounds(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per box, its image bounds (u0, u1, v0, v1), and whether it is at least partly in
        front."""
        R, t = pose[:3, :3], pose[:3, 3]
        cam = (self.corners - t) @ R  # world -> camera: R^T (p - t), as row vectors
        z = cam[..., 2]
        front = z.max(axis=1) > NEAR_M
        all_front = z.min(axis=1) > NEAR_M
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam[..., 0] / z * self.intr.fx + self.intr.cx
            v = cam[..., 1] / z * self.intr.fy + self.intr.cy
        big = 1e9
        rect = np.stack([u.min(axis=1), u.max(axis=1), v.min(axis=1), v.max(axis=1)], axis=1)
        rect[~all_front] = [-big, big, -big, big]
        return rect, front

    def render(
        self, pose: np.ndarray, exposure: float, noise_std: float, noise_rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(colour uint8 (H, W, 3), z-depth float32 (H, W), labels uint8 (H, W)) for ``pose``."""
        m, intr = self.model, self.intr
        origins, dirs = pixel_rays(intr, pose)
        origin = origins[0, 0]
        d = dirs.reshape(-1, 3)
        n = len(d)

        t_shell, s_axis, s_side = interior_exit(origin[None, :], d, m.lo, m.hi)
        box_idx = np.full(n, -1, dtype=np.int64)
        box_t = np.full(n, np.inf)
        rect, front = self._projected_bounds(pose)
        for x0, x1, y0, y1, idx in self.tiles:
            cand = np.nonzero(
                front
                & (rect[:, 1] >= x0 - 1)
                & (rect[:, 0] <= x1)
                & (rect[:, 3] >= y0 - 1)
                & (rect[:, 2] <= y1)
            )[0]
            if len(cand) == 0:
                continue
            t_hit, local_idx = m.solids.subset(cand).closest_hit(origin, d[idx], t_shell[idx])
            hit = local_idx >= 0
            box_idx[idx[hit]] = cand[local_idx[hit]]
            box_t[idx[hit]] = t_hit[hit]

        t = t_shell.copy()
        axis = s_axis.copy()
        normal = np.zeros((n, 3))
        normal[np.arange(n), s_axis] = -s_side
        labels = np.where(s_axis == 2, np.where(s_side < 0, FLOOR, CEILING), WALL).astype(np.uint8)
        mat = np.where(
            s_axis == 2,
            np.where(s_side < 0, m.shell_material[1], m.shell_material[2]),
            m.shell_material[0],
        )
        points = origin + t[:, None] * d
        local = points.copy()

        on_box = np.nonzero(box_idx >= 0)[0]
        if len(on_box):
            bi = box_idx[on_box]
            tb, loc_b, ax_b, nrm_b = m.solids.surface(origin, d[on_box], bi, box_t[on_box])
            t[on_box] = tb
            axis[on_box] = ax_b
            local[on_box] = loc_b
            normal[on_box] = nrm_b
            labels[on_box] = m.labels[bi]
            mat[on_box] = m.material[bi]
            points[on_box] = origin + tb[:, None] * d[on_box]

        rho = albedo(m.materials, mat, local, axis)
        chunks = [idx for *_, idx in self.tiles]
        e = irradiance(
            points,
            normal,
            m.lights,
            m.ambient,
            m.falloff_m,
            self.casters,
            self.caster_bounds,
            chunks,
        )
        linear = rho * e + m.materials["emission"][mat][:, None] * rho
        rgb = np.clip(exposure * linear, 0.0, 1.0) ** (1 / 2.2)
        if noise_std > 0:
            rgb = rgb + noise_rng.normal(0.0, noise_std, rgb.shape)
        color = (
            np.clip(np.round(rgb * 255.0), 0, 255)
            .astype(np.uint8)
            .reshape(intr.height, intr.width, 3)
        )
        depth = t.astype(np.float32).reshape(intr.height, intr.width)
        return color, depth, labels.reshape(intr.height, intr.width)
