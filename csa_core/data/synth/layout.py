"""Room layout: a rectangular room and furniture groups placed in it without overlaps.

World frame: metres, z up, the room spans [0, width] x [0, depth] x [0, height]. Walls are
numbered 0 (y = 0), 1 (x = width), 2 (y = depth), 3 (x = 0). Groups are placed one by one
in the family's order; each must keep clear of every group placed before it (world
bounding boxes, with a margin), so no two pieces of furniture interpenetrate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from csa_core.data.synth.families import RoomFamily
from csa_core.data.synth.floorplan import CELL_M, FloorGrid
from csa_core.data.synth.furniture import BUILDERS, FALLBACKS, Group, Part

# Yaw that turns a group's back (+y) towards each wall's outward normal.
WALL_YAW = (math.pi, -math.pi / 2, 0.0, math.pi / 2)

FLOOR_GAP_M = 0.06  # clearance between floor-standing groups
FREE_GAP_M = 0.6  # extra walking room around free-standing groups
ATTEMPTS = 40
MIN_WALKABLE_FRACTION = 0.15  # of the floor area: where the camera can stand, kept free
MIN_WALKABLE_M2 = 2.0


@dataclass(frozen=True)
class PlacedGroup:
    """A group with its pose in the room: position of its footprint centre and yaw."""

    group: Group
    x: float
    y: float
    yaw: float
    wall: int | None

    def world_parts(self) -> list[tuple[np.ndarray, np.ndarray, float, Part]]:
        """(centre, half-extents, yaw, part) of every part in world coordinates."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        out = []
        for p in self.group.parts:
            x, y, z = p.center
            centre = np.array([c * x - s * y + self.x, s * x + c * y + self.y, z])
            out.append((centre, np.asarray(p.half, dtype=np.float64), self.yaw + p.yaw, p))
        return out

    def footprint(self, grid: FloorGrid) -> np.ndarray:
        """Floor cells covered by the group's parts."""
        cells = np.zeros_like(grid.occupied)
        for centre, _, yaw, part in self.world_parts():
            cells |= grid.footprint(centre, part.planar_half(), yaw)
        return cells

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounds of the group, its keep-out volume included."""
        return _rotated_aabb(*self.group.bounds(), self.x, self.y, self.yaw)

    @property
    def on_floor(self) -> bool:
        return self.group.mount != "onwall"


@dataclass
class Room:
    width: float
    depth: float
    height: float
    groups: list[PlacedGroup] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    floor: FloorGrid = field(init=False)

    def __post_init__(self) -> None:
        self.floor = FloorGrid(self.width, self.depth)

    @property
    def lo(self) -> np.ndarray:
        return np.zeros(3)

    @property
    def hi(self) -> np.ndarray:
        return np.array([self.width, self.depth, self.height])

    def wall_length(self, wall: int) -> float:
        return self.width if wall in (0, 2) else self.depth


def _rotated_aabb(
    lo: np.ndarray, hi: np.ndarray, x: float, y: float, yaw: float
) -> tuple[np.ndarray, np.ndarray]:
    c, s = math.cos(yaw), math.sin(yaw)
    xs = np.array([lo[0], hi[0], lo[0], hi[0]])
    ys = np.array([lo[1], lo[1], hi[1], hi[1]])
    wx, wy = c * xs - s * ys + x, s * xs + c * ys + y
    return np.array([wx.min(), wy.min(), lo[2]]), np.array([wx.max(), wy.max(), hi[2]])


def _overlaps(
    lo: np.ndarray, hi: np.ndarray, others: list[tuple[np.ndarray, np.ndarray]], gap: float
) -> bool:
    for olo, ohi in others:
        if np.all(lo < ohi + gap) and np.all(olo < hi + gap):
            return True
    return False


def _wall_pose(
    room: Room, group: Group, wall: int, along: float, gap: float
) -> tuple[float, float]:
    lo, hi = group.bounds()
    half_d = (hi[1] - lo[1]) / 2 + gap
    if wall == 0:
        return along, half_d
    if wall == 1:
        return room.width - half_d, along
    if wall == 2:
        return along, room.depth - half_d
    return half_d, along


def _leaves_room_to_walk(room: Room, cand: PlacedGroup) -> bool:
    if not cand.on_floor:
        return True
    walk = room.floor.walkable(room.floor.occupied | cand.footprint(room.floor))
    need = max(MIN_WALKABLE_M2, MIN_WALKABLE_FRACTION * room.width * room.depth)
    return walk.sum() * CELL_M**2 >= need


def _try_place(room: Room, group: Group, rng: np.random.Generator) -> PlacedGroup | None:
    lo, hi = group.bounds()
    width = hi[0] - lo[0]
    placed_boxes = [g.aabb() for g in room.groups]
    floor_boxes = [g.aabb() for g in room.groups if g.on_floor]
    lengths = np.array([room.wall_length(k) for k in range(4)])
    for _ in range(ATTEMPTS):
        if group.mount == "free":
            yaw = float(rng.uniform(0, 2 * math.pi))
            half = _rotated_aabb(lo, hi, 0.0, 0.0, yaw)[1][:2]
            margin = half + 0.15
            if np.any(2 * margin >= [room.width, room.depth]):
                continue
            x = float(rng.uniform(margin[0], room.width - margin[0]))
            y = float(rng.uniform(margin[1], room.depth - margin[1]))
            cand = PlacedGroup(group, x, y, yaw, None)
            if _overlaps(*cand.aabb(), floor_boxes, FREE_GAP_M) or _overlaps(
                *cand.aabb(), placed_boxes, FLOOR_GAP_M
            ):
                continue
            if _leaves_room_to_walk(room, cand):
                return cand
            continue
        wall = int(rng.choice(4, p=lengths / lengths.sum()))
        end_margin = 0.3 if group.kind in ("door", "window") else 0.03
        free_len = room.wall_length(wall) - width - 2 * end_margin
        if free_len <= 0:
            continue
        along = end_margin + width / 2 + float(rng.uniform(0, free_len))
        gap = 0.003 if group.mount == "onwall" else 0.01
        x, y = _wall_pose(room, group, wall, along, gap)
        cand = PlacedGroup(group, x, y, WALL_YAW[wall], wall)
        clearance = FLOOR_GAP_M if group.mount == "wall" else 0.02
        if not _overlaps(*cand.aabb(), placed_boxes, clearance) and _leaves_room_to_walk(
            room, cand
        ):
            return cand
    return None


def build_room(family: RoomFamily, rng: np.random.Generator, free_groups: bool = True) -> Room:
    """Draw a room of ``family``: size, then each furniture group in the family's order.

    Groups that find no free spot after a number of tries are left out (listed in
    ``Room.skipped``). ``free_groups=False`` leaves out free-standing groups, the fallback
    when a crowded room leaves the camera no path.
    """
    room = Room(
        width=float(rng.uniform(*family.width_m)),
        depth=float(rng.uniform(*family.depth_m)),
        height=float(rng.uniform(*family.height_m)),
    )
    for kind, lo, hi in family.furniture:
        for _ in range(int(rng.integers(lo, hi + 1))):
            group = BUILDERS[kind](rng)
            if group.mount == "free" and not free_groups:
                continue
            placed = _try_place(room, group, rng)
            if placed is None and kind in FALLBACKS:
                placed = _try_place(room, FALLBACKS[kind](rng), rng)
            if placed is None:
                room.skipped.append(kind)
                continue
            room.groups.append(placed)
            if placed.on_floor:
                room.floor.occupied |= placed.footprint(room.floor)
    return room
