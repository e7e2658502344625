"""Capture modes: a hand-held style camera walk through free space, looking at furniture
("walk"), or viewpoints spread at random through the room ("random", :func:`random_views`).

In the walk, the camera moves along a smooth route (Catmull-Rom through random waypoints) that keeps
a clearance from walls and from every floor-standing part, at a fixed height with a
little bob, a few centimetres per frame. Its gaze moves smoothly from one piece of
furniture to the next, preferring classes it has not looked at yet, with the yaw rate
bounded so consecutive frames overlap a lot. Poses are camera-to-world, OpenCV axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from csa_core.data.synth.families import RoomFamily
from csa_core.data.synth.floorplan import CELL_M, CLEARANCE_M, FloorGrid
from csa_core.data.synth.layout import Room

MIN_TARGET_DIST_M = 1.0
SEGMENT_M = (0.8, 2.5)  # length range of straight legs between waypoints


class NoPathError(RuntimeError):
    """The room leaves no free space to walk in."""


@dataclass(frozen=True)
class Target:
    """A point the camera may look at, the class it shows, its group, and how far away the
    camera must be to pick it."""

    point: np.ndarray
    label: str
    group: int
    min_dist: float = MIN_TARGET_DIST_M


def _segment_clear(
    clear: np.ndarray, grid: FloorGrid, a: np.ndarray, b: np.ndarray, need: float
) -> bool:
    n = max(2, int(np.linalg.norm(b - a) / (CELL_M / 2)) + 1)
    pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    i, j = grid.cell_of(pts)
    return bool(np.all(clear[i, j] >= need))


def _catmull_rom(points: np.ndarray, per_segment: int = 40) -> np.ndarray:
    """Dense samples of the open uniform Catmull-Rom curve through ``points`` (k, 2)."""
    ext = np.vstack([2 * points[0] - points[1], points, 2 * points[-1] - points[-2]])
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)[:, None]
    out = []
    for i in range(1, len(ext) - 2):
        p0, p1, p2, p3 = ext[i - 1], ext[i], ext[i + 1], ext[i + 2]
        out.append(
            0.5
            * (
                (2 * p1)
                + (-p0 + p2) * t
                + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3
            )
        )
    out.append(points[-1:])
    return np.concatenate(out)


def walk_route(room: Room, length: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth open route (m, 2) through walkable space, about ``length`` metres long or
    as long as the free space allows; every sample keeps the camera's clearance.

    Waypoints form a chain of straight legs that each stay in free space, turning by
    less than ~100 degrees; the chain is then smoothed (Catmull-Rom) where that stays clear.
    """
    grid = room.floor
    clear = grid.clearance()
    walk = grid.walkable()
    if walk.sum() < 20:
        raise NoPathError("no free floor space for the camera")
    centres = np.stack([grid.gx[walk], grid.gy[walk]], axis=-1)
    roomy = clear[walk] >= CLEARANCE_M + 0.15
    cells = centres[roomy] if roomy.sum() >= 10 else centres
    margin = CLEARANCE_M + 0.03
    way = [cells[rng.integers(len(cells))]]
    heading: np.ndarray | None = None
    total = 0.0
    for _ in range(12):
        if total >= length:
            break
        found = None
        for min_len, min_cos in ((SEGMENT_M[0], -0.17), (0.5, -0.6)):
            d = cells - way[-1]
            dist = np.linalg.norm(d, axis=1)
            ok = (dist >= min_len) & (dist <= SEGMENT_M[1])
            if heading is not None:
                ok &= (d @ heading) / np.maximum(dist, 1e-9) > min_cos
            options = np.nonzero(ok)[0]
            for k in rng.permutation(options)[:150]:
                if _segment_clear(clear, grid, way[-1], cells[k], margin):
                    found = cells[k]
                    break
            if found is not None:
                break
        if found is None:
            break
        heading = (found - way[-1]) / np.linalg.norm(found - way[-1])
        total += float(np.linalg.norm(found - way[-1]))
        way.append(found)
    if len(way) == 1:
        a = np.linspace(0, 2 * np.pi, 60)
        r = max(0.03, min(0.3, float(clear[walk].max()) - CLEARANCE_M))
        best = centres[np.argmax(clear[walk])]
        return best + r * np.stack([np.cos(a), np.sin(a)], axis=-1)
    way_arr = np.array(way)
    if len(way_arr) >= 3:
        smooth = _catmull_rom(way_arr)
        i, j = grid.cell_of(smooth)
        if np.all(clear[i, j] >= CLEARANCE_M):
            return smooth
    return _densify(way_arr)


def _densify(points: np.ndarray, step: float = 0.02) -> np.ndarray:
    out = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        n = max(1, int(np.linalg.norm(b - a) / step))
        out.append(a + np.linspace(0.0, 1.0, n, endpoint=False)[:, None] * (b - a))
    out.append(points[-1:])
    return np.concatenate(out)


def furniture_targets(room: Room) -> list[Target]:
    """One look-at point per (group, class): the middle of that class's parts in the group."""
    targets = []
    for gi, g in enumerate(room.groups):
        by_label: dict[str, list[np.ndarray]] = {}
        for centre, half, _, part in g.world_parts():
            by_label.setdefault(part.label, []).extend([centre - half, centre + half])
        for label, pts in by_label.items():
            arr = np.array(pts)
            mid = (arr.min(axis=0) + arr.max(axis=0)) / 2
            targets.append(Target(mid, label, gi, MIN_TARGET_DIST_M if g.on_floor else 1.6))
    return targets


def _resample_route(route: np.ndarray, step: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit directions of travel at arc lengths i * step, walking the route
    back and forth when it is shorter than the walk."""
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = max(s[-1], 1e-9)
    q = np.mod(step * np.arange(n), 2 * total)
    forward = q <= total
    q = np.where(forward, q, 2 * total - q)
    x, y = np.interp(q, s, route[:, 0]), np.interp(q, s, route[:, 1])
    ahead = np.clip(q + 0.05, 0.0, total)
    tan = np.stack(
        [np.interp(ahead, s, route[:, 0]) - x, np.interp(ahead, s, route[:, 1]) - y], axis=-1
    )
    tan[~forward] *= -1
    norm = np.linalg.norm(tan, axis=1, keepdims=True)
    tan = np.where(norm > 1e-9, tan / np.maximum(norm, 1e-9), [1.0, 0.0])
    return np.stack([x, y], axis=-1), tan


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _choose_targets(
    pos: np.ndarray,
    heading: np.ndarray,
    targets: list[Target],
    hold: int,
    half_fov: float,
    rng: np.random.Generator,
) -> list[Target]:
    """One target per block of ``hold`` frames.

    Prefers targets that need little turning, a couple of metres away, whose class and
    group have not been in view yet (everything inside the field of view of a chosen gaze
    counts as seen), so a short walk still shows many classes.
    """
    if not targets:
        targets = [
            Target(
                np.array([pos[0, 0] + heading[0, 0], pos[0, 1] + heading[0, 1], 1.0]),
                "none",
                -1,
                0.0,
            )
        ]
    pts = np.array([t.point[:2] for t in targets])
    min_dist = np.array([t.min_dist for t in targets])
    seen: dict[str, float] = {}
    seen_group: dict[int, float] = {}
    gaze = math.atan2(heading[0, 1], heading[0, 0])
    chosen: list[Target] = []
    for start in range(0, len(pos), hold):
        p = pos[min(start + hold // 2, len(pos) - 1)]
        d = pts - p
        dist = np.hypot(d[:, 0], d[:, 1])
        ang = np.arctan2(d[:, 1], d[:, 0])
        novelty = np.array(
            [1.2 * seen.get(t.label, 0.0) + 0.7 * seen_group.get(t.group, 0.0) for t in targets]
        )
        score = (
            np.abs(_wrap(ang - gaze))
            + novelty
            + 0.4 * np.maximum(0.0, 2.0 - dist)
            + 0.6 * rng.random(len(targets))
        )
        score[dist < min_dist] = np.inf
        k = int(np.argmin(score))
        if not np.isfinite(score[k]):
            k = int(np.argmax(dist))
        chosen.append(targets[k])
        gaze = float(ang[k])
        in_view = (np.abs(_wrap(ang - gaze)) < 0.8 * half_fov) & (dist > 0.5)
        for j in np.nonzero(in_view)[0]:
            seen[targets[j].label] = seen.get(targets[j].label, 0.0) + 1.0
            seen_group[targets[j].group] = seen_group.get(targets[j].group, 0.0) + 1.0
    return chosen


def _smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    if len(x) < 3 or sigma <= 0:
        return x
    r = int(3 * sigma)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    padded = np.concatenate([np.full(r, x[0]), x, np.full(r, x[-1])])
    return np.convolve(padded, k, mode="valid")


def _rate_limit(x: np.ndarray, max_step: float) -> np.ndarray:
    out = x.copy()
    for i in range(1, len(out)):
        out[i] = out[i - 1] + np.clip(out[i] - out[i - 1], -max_step, max_step)
    return out


def look_at_pose(position: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) in a z-up world."""
    fwd = np.array(
        [math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)]
    )
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, fwd, position
    return pose


def camera_walk(
    room: Room, family: RoomFamily, frames: int, rng: np.random.Generator
) -> np.ndarray:
    """Poses (frames, 4, 4) of a smooth walk through ``room`` looking at its furniture."""
    route = walk_route(room, family.step_m * frames, rng)
    pos2, heading = _resample_route(route, family.step_m, frames)
    height = rng.uniform(*family.camera_height_m)
    bob = 0.015 * np.sin(np.arange(frames) * 0.9 + rng.uniform(0, 2 * np.pi))
    pos = np.column_stack([pos2, height + bob])

    hold = family.target_frames
    chosen = _choose_targets(
        pos2, heading, furniture_targets(room), hold, math.radians(family.hfov_deg) / 2, rng
    )
    look = np.zeros((frames, 3))
    for i in range(frames):
        b = i // hold
        a = min(1.0, (i - b * hold) / max(1.0, 0.6 * hold))
        w = a * a * (3 - 2 * a)
        prev = chosen[b - 1].point if b > 0 else chosen[0].point
        look[i] = (1 - w) * prev + w * chosen[b].point
    d = look - pos
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    pitch = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    yaw = _rate_limit(_smooth(yaw, 2.0), math.radians(family.max_turn_deg))
    pitch = _rate_limit(
        np.clip(_smooth(pitch, 2.0), math.radians(-35), math.radians(12)), math.radians(2.0)
    )
    return np.stack([look_at_pose(pos[i], float(yaw[i]), float(pitch[i])) for i in range(frames)])


# ---- random viewpoints --------------------------------------------------------------------

RANDOM_CLEARANCE_M = 0.3  # horizontal distance kept from walls and every floor-standing part
RANDOM_HEIGHT_M = (0.6, 1.9)  # camera heights: from a crouch to a raised arm
MIN_LOOK_M = 0.5  # nearest target distance
NEAR_WALL_M = 0.3  # a view whose rays mostly stop closer than this sees only a wall or a part
NEAR_SHARE = 0.3  # largest share of probe rays allowed to stop that close
VIEW_TRIES = 60


def _probe_dirs(pose: np.ndarray, hfov_deg: float, nx: int = 9, ny: int = 7) -> np.ndarray:
    """World directions of an ``nx`` x ``ny`` grid of rays spread over a 4:3 image."""
    half = math.tan(math.radians(hfov_deg) / 2)
    u, v = np.meshgrid(np.linspace(-half, half, nx), np.linspace(-0.75 * half, 0.75 * half, ny))
    cam = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=-1)
    return cam @ pose[:3, :3].T


def _random_target(room: Room, rng: np.random.Generator) -> np.ndarray:
    """A point inside a random piece of furniture's bounds (three times in four) or anywhere in
    the room below 2 m."""
    if room.groups and rng.random() < 0.75:
        lo, hi = room.groups[int(rng.integers(len(room.groups)))].aabb()
        lo, hi = np.maximum(lo, 0.0), np.minimum(hi, room.hi)
        return lo + rng.random(3) * (hi - lo)
    return rng.random(3) * np.array([room.width, room.depth, min(2.0, room.height)])


def random_views(
    room: Room, family: RoomFamily, frames: int, rng: np.random.Generator
) -> np.ndarray:
    """Poses (frames, 4, 4) spread at random through the room's free space, each looking at a
    random target.

    A camera stands anywhere at least ``RANDOM_CLEARANCE_M`` (horizontally) from the walls and
    from every floor-standing part, at a height in ``RANDOM_HEIGHT_M`` (below the ceiling),
    and looks at a target at least ``MIN_LOOK_M`` away with a small random roll. A pose whose
    probe rays (a 9 x 7 grid over the view) mostly stop within ``NEAR_WALL_M`` (more than
    ``NEAR_SHARE`` of them), or that sees nothing but wall, is drawn again (after
    ``VIEW_TRIES`` draws the best one is kept). Consecutive frames are unrelated: this is a
    capture from everywhere, not a walk.
    """
    from csa_core.data.synth.boxes import interior_exit
    from csa_core.data.synth.render import room_solids

    grid = room.floor
    clear = grid.clearance()
    free = clear >= RANDOM_CLEARANCE_M
    if free.sum() < 4:
        raise NoPathError("no free floor space for the camera")
    cells = np.stack([grid.gx[free], grid.gy[free]], axis=-1)
    solids, sources = room_solids(room)
    is_wall = np.array(
        [room.groups[gi].group.mount == "onwall" for gi, _ in sources] + [True], dtype=bool
    )
    top = min(RANDOM_HEIGHT_M[1], room.height - 0.3)
    poses = np.zeros((frames, 4, 4))
    for i in range(frames):
        best, best_score = None, np.inf
        for _ in range(VIEW_TRIES):
            xy = cells[rng.integers(len(cells))] + rng.uniform(-CELL_M / 2, CELL_M / 2, 2)
            pos = np.array([xy[0], xy[1], rng.uniform(RANDOM_HEIGHT_M[0], top)])
            target = _random_target(room, rng)
            d = target - pos
            if np.linalg.norm(d) < MIN_LOOK_M:
                continue
            yaw = math.atan2(d[1], d[0])
            pitch = math.atan2(d[2], math.hypot(d[0], d[1]))
            pose = look_at_pose(pos, yaw, pitch)
            roll = float(np.clip(rng.normal(0.0, math.radians(4.0)), -0.2, 0.2))
            c, s = math.cos(roll), math.sin(roll)
            pose[:3, :2] = pose[:3, :2] @ np.array([[c, s], [-s, c]])
            dirs = _probe_dirs(pose, family.hfov_deg)
            t_shell, axis, _ = interior_exit(pos[None, :], dirs, room.lo, room.hi)
            t, idx = solids.closest_hit(pos, dirs, t_shell)
            dist = np.where(idx >= 0, t, t_shell) * np.linalg.norm(dirs, axis=1)
            near = float(np.mean(dist < NEAR_WALL_M))
            only_wall = bool(np.all(np.where(idx >= 0, is_wall[idx], axis != 2)))
            score = near + (1.0 if only_wall else 0.0)
            if near <= NEAR_SHARE and not only_wall:
                best = pose
                break
            if score < best_score:
                best, best_score = pose, score
        if best is None:
            raise NoPathError("no camera pose sees the room")
        poses[i] = best
    return poses


CAPTURES = ("walk", "random")


def capture_poses(
    room: Room, family: RoomFamily, frames: int, rng: np.random.Generator, capture: str = "walk"
) -> np.ndarray:
    """Camera poses of a capture mode: "walk" (:func:`camera_walk`) or "random"
    (:func:`random_views`)."""
    if capture == "random":
        return random_views(room, family, frames, rng)
    return camera_walk(room, family, frames, rng)
