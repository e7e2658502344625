"""Ground-truth labels defined in 3D for scenes that have none: "space labels".

A real capture without annotations (the 7-Scenes kitchen) still has real geometry and real
sensor depth. To score label fusion on it, every frame needs ground truth that is consistent
across views, as annotations of a real room would be. :func:`fit_space_labelling` builds a
fixed labelling of 3D space from the scene's own depth and poses, and :func:`space_labels`
reads it in every frame: the label of a pixel is the label of the 3D point that the pixel's
measured depth backprojects to, so the same point of space gets the same label in every view.
Pixels without depth are 0 (unknown).

How space is labelled (every step uses only depth, poses and intrinsics; never colour, never
labels, never a fuser):

1. **Fused points.** Each frame's depth is backprojected to world points with normals (from
   central differences of the camera points, turned to face the camera); points and unit
   normals are averaged per ``voxel`` cell over all frames. Cells seen fewer than
   ``min_observations`` times are dropped (flying pixels).
2. **Up.** The mean "up" of the cameras (the negated image y axis; people hold cameras
   roughly upright, but often pitched down) is refined to the direction that the
   near-horizontal cells' normals lie along and the near-vertical cells' normals lie across
   (within ``horizontal_deg``, three rounds), so a world frame in any orientation (7-Scenes:
   about y-down) and cameras looking down at a table are handled.
3. **Floor** (NYU40 ``floor``, 2): the lowest height at which upward-facing horizontal cells
   cover at least ``floor_min_area`` m², at least ``floor_below_camera`` below the cameras'
   median height, refined to a least-squares plane of the cells there (which absorbs a small
   error of up). Every point less than ``floor_band`` above that plane, or below it, is floor.
   **Ceiling** (22): the same from above with downward-facing cells, at least
   ``ceiling_above_camera`` above the cameras. Without such cells there is no floor (ceiling).
4. **Walls** (``wall``, 1): near-vertical planes found greedily among the other cells
   (dominant horizontal normal directions, then dominant offsets along each, then a
   least-squares plane) whose cells cover at least ``wall_min_area`` m², span at least
   ``wall_min_width`` by ``wall_min_height`` m, and have almost nothing behind them (at most
   ``wall_max_behind`` as many cells in their extent lie more than ``wall_behind`` behind the
   plane as on it: an outer boundary of the room). A plane standing more than ``wall_behind``
   in front of a parallel wall over half its width is dropped (a cabinet front). A point is
   wall when it lies within the plane's extent (plus ``wall_margin``) and between
   ``wall_behind`` behind the plane and ``wall_band`` in front of it.
5. **Furniture and objects.** The rest of space is cut into furniture cells: a Voronoi
   partition (nearest seed) of ``furniture_per_m2`` seeds per m² of remaining surface (the
   remaining cells' area, counts bounded by ``furniture``), drawn from the remaining cells.
   Object balls are carved out of them: ``objects_per_m2`` seeds (bounded by ``objects``) with
   radii log-uniform in ``object_radius``; a point inside balls belongs to the one with the
   smallest ``|p - s_j| / r_j`` (small objects on counters, on tables, on walls). Furniture
   cells get classes from :data:`FURNITURE_CLASSES`, balls from :data:`OBJECT_CLASSES`, each
   drawn with Zipf-like frequencies (weight 1 / rank). Cell sizes vary with the seeds' spacing
   and ball radii span almost a decade, so shares span orders of magnitude and several classes
   cover well under 1% of the pixels, as small objects do in real rooms.

Everything random derives from ``seed``, so a scene and a seed give the same labels on every
run. The measured depth carries the sensor's noise, so near a region boundary a point can fall
on either side in different views, as annotations of a real mesh seen through noisy depth do.

Limits: the labels follow space, not real objects. Floor, ceiling and walls are found as
planes and are close to the real ones; the object regions are blobs and cells that cut across
real objects (half a cabinet, a patch of counter with a chair label), so a fuser scored on
them is rewarded for multi-view consistency on real geometry and real depth noise, not for
recognising objects. Region boundaries are spheres and planes through free space, smooth and
often far from depth edges, so they are easier to fuse than real object boundaries, and
there is no class that a network would confuse with another. Walls and floor swallow what lies
flush on them (doors, pictures, windows, floor mats). The labelling depends on the frames it is
built from (their number and working resolution change the fused cells a little, so the labels move
a little).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from csa_core.data.camera import Intrinsics
from csa_core.data.nyu40 import class_id
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene, require_depth
from csa_core.errors import CSAInputError, check_seed

WALL, FLOOR, CEILING = class_id("wall"), class_id("floor"), class_id("ceiling")

# Classes of the furniture cells and of the object balls, most frequent first (their Zipf
# rank): as in indoor scans, a few furniture classes cover most of the non-structural surface
# and many small object classes cover little each.
FURNITURE_CLASSES: tuple[int, ...] = tuple(
    class_id(n)
    for n in (
        "cabinet", "table", "counter", "chair", "otherfurniture", "shelves", "door",
        "refrigerator", "desk", "window", "bookshelf", "sofa", "otherstructure", "dresser",
    )
)  # fmt: skip
OBJECT_CLASSES: tuple[int, ...] = tuple(
    class_id(n)
    for n in (
        "otherprop", "box", "books", "picture", "sink", "lamp", "towel", "bag", "paper",
        "television", "clothes", "pillow", "mirror", "whiteboard",
    )
)  # fmt: skip

_FURNITURE, _OBJECTS, _STREAMS = 0, 1, 2  # random streams, one role each (and their number)


@dataclass
class SpaceLabelConfig:
    """How space is labelled (module docstring). Lengths in metres, areas in m², angles in
    degrees."""

    voxel: float = 0.04
    min_observations: int = 2
    max_points_per_frame: int = 20000  # frames are subsampled on a pixel grid beyond this
    normal_step_px: int = 2  # half baseline of the central differences, at 160 px width
    horizontal_deg: float = 20.0
    vertical_deg: float = 20.0
    floor_min_area: float = 0.25
    floor_below_camera: float = 0.9
    ceiling_above_camera: float = 0.3
    floor_band: float = 0.06
    wall_min_area: float = 1.0
    wall_min_width: float = 1.0
    wall_min_height: float = 1.0
    wall_band: float = 0.06
    wall_behind: float = 0.25
    wall_max_behind: float = 0.1
    wall_margin: float = 0.1
    max_walls: int = 8
    furniture_per_m2: float = 1.0
    furniture: tuple[int, int] = (4, 64)  # fewest and most furniture regions
    objects_per_m2: float = 1.5
    objects: tuple[int, int] = (4, 128)  # fewest and most object regions
    object_radius: tuple[float, float] = (0.04, 0.3)

    def __post_init__(self) -> None:
        for name in ("voxel", "floor_band", "wall_band", "wall_behind"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SpaceLabelConfig: {name} must be > 0, got {getattr(self, name)}")
        for name in ("furniture_per_m2", "objects_per_m2"):
            if not getattr(self, name) >= 0:
                raise ValueError(
                    f"SpaceLabelConfig: {name} must be >= 0, got {getattr(self, name)}"
                )
        lo, hi = self.object_radius
        if not 0 < lo <= hi:
            raise ValueError(
                f"SpaceLabelConfig: object_radius must be 0 < low <= high, got {self.object_radius}"
            )
        for name in ("furniture", "objects"):
            fewest, most = getattr(self, name)
            if not 0 <= fewest <= most:
                raise ValueError(
                    f"SpaceLabelConfig: {name} must be 0 <= fewest <= most, got {(fewest, most)}"
                )


@dataclass
class Plane:
    """The plane ``p . normal = offset`` (``normal`` a unit vector)."""

    normal: np.ndarray
    offset: float

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of points (N, 3), positive on the side ``normal`` points to."""
        return points @ self.normal - self.offset


@dataclass
class Wall(Plane):
    """A vertical plane (``normal`` facing the room) over ``t_range`` along ``tangent`` (the
    horizontal in-plane direction) and ``h_range`` in height along up."""

    tangent: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t_range: tuple[float, float] = (0.0, 0.0)
    h_range: tuple[float, float] = (0.0, 0.0)


@dataclass
class SpaceLabelling:
    """A labelling of 3D space: :meth:`label_points` gives the NYU40 id of any world point."""

    up: np.ndarray
    # Floor: normal about up; ceiling: normal about down. A point whose signed distance to
    # either is below ``floor_band`` (within the band or beyond the plane) is floor / ceiling.
    floor: Plane | None
    ceiling: Plane | None
    walls: list[Wall] = field(default_factory=list)
    furniture_seeds: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3)
    furniture_classes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))  # (K,)
    object_seeds: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3)
    object_radii: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (J,) metres
    object_classes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))  # (J,)
    config: SpaceLabelConfig = field(default_factory=SpaceLabelConfig)

    def structure(self, points: np.ndarray) -> np.ndarray:
        """(N,) uint8: floor, ceiling or wall id of each point (N, 3), 0 elsewhere (floor over
        ceiling over walls)."""
        cfg = self.config
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(p), dtype=np.uint8)
        h = p @ self.up
        m = cfg.wall_margin
        for wall in self.walls:
            s = wall.distance(p)
            t = p @ wall.tangent
            inside = (t >= wall.t_range[0] - m) & (t <= wall.t_range[1] + m)
            inside &= (h >= wall.h_range[0] - m) & (h <= wall.h_range[1] + m)
            out[inside & (s > -cfg.wall_behind) & (s < cfg.wall_band)] = WALL
        if self.ceiling is not None:
            out[self.ceiling.distance(p) < cfg.floor_band] = CEILING
        if self.floor is not None:
            out[self.floor.distance(p) < cfg.floor_band] = FLOOR
        return out

    def objects(self, points: np.ndarray, chunk: int = 32768) -> np.ndarray:
        """(N,) index of the object ball each point (N, 3) lies in (the one whose
        ``|p - s_j| / r_j`` is smallest, when below 1), -1 for none."""
        return _nearest(points, self.object_seeds, self.object_radii, chunk, within=True)

    def furniture(self, points: np.ndarray, chunk: int = 32768) -> np.ndarray:
        """(N,) index of the nearest furniture seed of each point (N, 3)."""
        return _nearest(points, self.furniture_seeds, None, chunk, within=False)

    def label_points(self, points: np.ndarray) -> np.ndarray:
        """(N,) uint8 NYU40 id of each world point (N, 3)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = self.structure(p)
        rest = np.flatnonzero(out == 0)
        if rest.size and len(self.object_seeds):
            j = self.objects(p[rest])
            out[rest[j >= 0]] = self.object_classes[j[j >= 0]]
            rest = rest[j < 0]
        if rest.size and len(self.furniture_seeds):
            out[rest] = self.furniture_classes[self.furniture(p[rest])]
        return out


def _nearest(
    points: np.ndarray, seeds: np.ndarray, radii: np.ndarray | None, chunk: int, within: bool
) -> np.ndarray:
    """Per point, the seed with the smallest distance (divided by its radius when given);
    with ``within``, -1 where that ratio is not below 1."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(p), -1, dtype=np.int64)
    if len(seeds) == 0:
        return out
    scale = np.ones(len(seeds)) if radii is None else 1.0 / np.asarray(radii, np.float64) ** 2
    for start in range(0, len(p), chunk):
        q = p[start : start + chunk]
        d2 = ((q[:, None, :] - seeds[None, :, :]) ** 2).sum(-1) * scale[None, :]
        best = np.argmin(d2, axis=1)
        if within:
            best[d2[np.arange(len(q)), best] >= 1.0] = -1
        out[start : start + chunk] = best
    return out


# ---- fused points ----------------------------------------------------------------------


def _camera_points(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    u, v = np.meshgrid(
        np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64)
    )
    z = depth.astype(np.float64)
    return np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=-1)


def _valid_depth(depth: np.ndarray) -> np.ndarray:
    return np.isfinite(depth) & (depth > 0)


def frame_points(frame: Frame, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """World points (H, W, 3) of a frame's depth and whether each pixel has depth."""
    if frame.depth is None:
        raise CSAInputError(f"frame {frame.name}", "space labels need depth")
    valid = _valid_depth(frame.depth)
    cam = _camera_points(np.where(valid, frame.depth, 0.0), intr)
    pose = np.asarray(frame.pose, dtype=np.float64)
    return cam @ pose[:3, :3].T + pose[:3, 3], valid


def _frame_normals(cam: np.ndarray, valid: np.ndarray, step: int) -> np.ndarray:
    """Unit camera-facing normals (H, W, 3) from central differences ``step`` pixels either
    side; NaN where a neighbour lacks depth or lies across a depth jump."""
    p = np.where(valid[..., None], cam, np.nan)
    pad = np.pad(p, ((step, step), (step, step), (0, 0)), constant_values=np.nan)
    h, w = valid.shape
    dx = pad[step : step + h, 2 * step :] - pad[step : step + h, :w]
    dy = pad[2 * step :, step : step + w] - pad[:h, step : step + w]
    z = cam[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        jump = (np.abs(dx[..., 2]) > 0.1 * z * step) | (np.abs(dy[..., 2]) > 0.1 * z * step)
        n = np.cross(dx, dy)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n[np.sum(n * cam, axis=-1) > 0] *= -1.0
    n[jump] = np.nan
    return n


def fuse_points(
    scene: Scene, config: SpaceLabelConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) and unit normals (M, 3; NaN where the views disagree) of the scene's
    depth, averaged per ``config.voxel`` cell over all frames (module docstring, step 1)."""
    cfg = config or SpaceLabelConfig()
    intr = scene.intrinsics
    stride = max(1, int(np.ceil(np.sqrt(intr.width * intr.height / cfg.max_points_per_frame))))
    step = max(1, int(round(cfg.normal_step_px * intr.width / 160)))
    pts, nrm = [], []
    for f in scene.frames:
        if f.depth is None:
            raise CSAInputError(f"frame {f.name}", "space labels need depth")
        valid = _valid_depth(f.depth)
        cam = _camera_points(np.where(valid, f.depth, 0.0), intr)
        n = _frame_normals(cam, valid, step)
        keep = np.zeros_like(valid)
        keep[::stride, ::stride] = True
        keep &= valid
        pose = np.asarray(f.pose, dtype=np.float64)
        pts.append(cam[keep] @ pose[:3, :3].T + pose[:3, 3])
        nrm.append(n[keep] @ pose[:3, :3].T)
    p = np.concatenate(pts) if pts else np.zeros((0, 3))
    n = np.concatenate(nrm) if nrm else np.zeros((0, 3))
    if len(p) == 0:
        return p, n
    keys = np.floor(p / cfg.voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    m = len(counts)
    mean_p = np.stack([np.bincount(inverse, p[:, k], minlength=m) for k in range(3)], axis=1)
    mean_p /= counts[:, None]
    has_n = np.isfinite(n).all(axis=1)
    nz = np.where(has_n[:, None], n, 0.0)
    sum_n = np.stack([np.bincount(inverse, nz[:, k], minlength=m) for k in range(3)], axis=1)
    n_count = np.bincount(inverse, has_n.astype(np.float64), minlength=m)
    with np.errstate(invalid="ignore", divide="ignore"):
        length = np.linalg.norm(sum_n, axis=1)
        agree = length / np.maximum(n_count, 1)  # 1: every view's normal the same
        mean_n = sum_n / length[:, None]
    mean_n[(n_count < 1) | (agree < 0.5)] = np.nan
    ok = counts >= cfg.min_observations
    return mean_p[ok], mean_n[ok]


# ---- structure: up, floor, ceiling, walls ----------------------------------------------


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def estimate_up(scene: Scene, normals: np.ndarray, config: SpaceLabelConfig) -> np.ndarray:
    """Unit world up: the cameras' mean up, refined to the direction that the near-horizontal
    cells' normals lie along and the near-vertical cells' normals lie across (the largest
    eigenvector of mean(n n^T) over the first minus mean(n n^T) over the second)."""
    up = np.mean([-np.asarray(f.pose, dtype=np.float64)[:3, 1] for f in scene.frames], axis=0)
    up = _unit(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
    n = normals[np.isfinite(normals).all(axis=1)]
    for deg in (2 * config.horizontal_deg, config.horizontal_deg, config.horizontal_deg):
        along = np.abs(n @ up)
        flat = n[along > np.cos(np.radians(deg))]
        upright = n[along < np.sin(np.radians(deg))]
        if len(flat) < 50:
            break
        m = flat.T @ flat / len(flat)
        if len(upright) >= 50:
            m -= upright.T @ upright / len(upright)
        refined = np.linalg.eigh(m)[1][:, -1]
        up = refined if refined @ up > 0 else -refined
    return _unit(up)


def _lowest_level(
    heights: np.ndarray, bin_size: float, min_count: float, limit: float
) -> float | None:
    """The lowest height at or below ``limit`` where ``heights`` pile up (at least
    ``min_count`` within three bins), refined to their median there."""
    heights = heights[heights <= limit + bin_size]
    if len(heights) < min_count:
        return None
    lo = heights.min()
    hist = np.bincount(np.floor((heights - lo) / bin_size).astype(np.int64))
    smooth = np.convolve(hist, np.ones(3), mode="same")
    for b in np.flatnonzero(smooth >= min_count):
        peak = max(0, b - 1) + int(np.argmax(hist[max(0, b - 1) : b + 2]))
        near = np.abs(heights - (lo + (peak + 0.5) * bin_size)) <= 1.5 * bin_size
        h = float(np.median(heights[near]))
        if h <= limit:
            return h
    return None


def _fit_plane(points: np.ndarray, normal: np.ndarray, offset: float, band: float) -> Plane:
    """Least-squares plane of the points within ``band`` of the plane (``normal``, ``offset``),
    refitted twice; its normal on ``normal``'s side."""
    plane = Plane(normal, offset)
    for _ in range(2):
        q = points[np.abs(plane.distance(points)) <= band]
        if len(q) < 3:
            break
        centre = q.mean(axis=0)
        n = np.linalg.eigh((q - centre).T @ (q - centre))[1][:, 0]
        n = n if n @ normal > 0 else -n
        plane = Plane(n, float(centre @ n))
    return plane


def _horizontal_plane(
    points: np.ndarray,
    facing: np.ndarray,
    direction: np.ndarray,
    limit: float,
    cfg: SpaceLabelConfig,
) -> Plane | None:
    """The lowest level along ``direction`` (up: floor, down: ceiling) of cells facing it,
    at or below ``limit`` along it, fitted as a plane."""
    cells = points[facing > np.cos(np.radians(cfg.horizontal_deg))]
    level = _lowest_level(cells @ direction, cfg.voxel, cfg.floor_min_area / cfg.voxel**2, limit)
    if level is None:
        return None
    return _fit_plane(cells, direction, level, 2 * cfg.voxel)


def _find_walls(
    points: np.ndarray, normals: np.ndarray, up: np.ndarray, cfg: SpaceLabelConfig
) -> list[Wall]:
    """Near-vertical planes (module docstring, step 4) among the cells ``points``."""
    has_n = np.isfinite(normals).all(axis=1)
    vertical = has_n.copy()
    vertical[has_n] = np.abs(normals[has_n] @ up) < np.sin(np.radians(cfg.vertical_deg))
    if vertical.sum() == 0:
        return []
    e1 = _unit(np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0]))
    e2 = np.cross(up, e1)
    vp, vn = points[vertical], normals[vertical]
    azimuth = np.degrees(np.arctan2(vn @ e2, vn @ e1)) % 360.0
    min_cells = cfg.wall_min_area / cfg.voxel**2
    hist = np.bincount(np.floor(azimuth / 5.0).astype(np.int64) % 72, minlength=72).astype(float)
    hist = hist + np.roll(hist, 1) + np.roll(hist, -1)
    heights = points @ up
    walls: list[Wall] = []
    while len(walls) < cfg.max_walls:  # dominant normal directions, fullest first
        b = int(np.argmax(hist))
        if hist[b] < min_cells:
            break
        hist[[(b + k) % 72 for k in range(-4, 5)]] = 0.0  # this direction, +- 20 degrees
        diff = np.abs((azimuth - (b + 0.5) * 5.0 + 180.0) % 360.0 - 180.0)
        sel = diff < 15.0
        if sel.sum() < min_cells:
            continue
        mean_n = vn[sel].mean(axis=0)
        direction = _unit(mean_n - (mean_n @ up) * up)
        offsets = vp[sel] @ direction
        lo = offsets.min()
        d_hist = np.bincount(np.floor((offsets - lo) / cfg.voxel).astype(np.int64)).astype(float)
        d_hist = np.convolve(d_hist, np.ones(3), mode="same")
        while len(walls) < cfg.max_walls:  # planes along this direction, fullest first
            k = int(np.argmax(d_hist))
            if d_hist[k] < min_cells:
                break
            d_hist[max(0, k - 3) : k + 4] = 0.0
            plane = _fit_plane(vp[sel], direction, lo + (k + 0.5) * cfg.voxel, 1.5 * cfg.voxel)
            q = vp[sel][np.abs(plane.distance(vp[sel])) <= 1.5 * cfg.voxel]
            if len(q) < min_cells or abs(plane.normal @ up) > np.sin(np.radians(cfg.vertical_deg)):
                continue
            tangent = _unit(np.cross(up, plane.normal))
            t, h = q @ tangent, q @ up
            t_range = (float(np.percentile(t, 1)), float(np.percentile(t, 99)))
            h_range = (float(np.percentile(h, 1)), float(np.percentile(h, 99)))
            if (
                t_range[1] - t_range[0] < cfg.wall_min_width
                or h_range[1] - h_range[0] < cfg.wall_min_height
            ):
                continue
            # An outer boundary of the room: few cells of its extent lie behind it.
            ta = points @ tangent
            in_extent = (ta >= t_range[0]) & (ta <= t_range[1])
            in_extent &= (heights >= h_range[0]) & (heights <= h_range[1])
            behind = in_extent & (plane.distance(points) < -cfg.wall_behind)
            if behind.sum() > cfg.wall_max_behind * len(q):
                continue
            walls.append(Wall(plane.normal, plane.offset, tangent, t_range, h_range))
    return [w for w in walls if not any(_in_front(w, other, cfg.wall_behind) for other in walls)]


def _in_front(wall: Wall, other: Wall, gap: float) -> bool:
    """Whether ``wall`` stands more than ``gap`` in front of the parallel, same-facing ``other``
    over at least half its width (a cabinet front before the wall it stands against)."""
    if wall.normal @ other.normal < np.cos(np.radians(10.0)):
        return False
    if wall.offset - other.offset <= gap:
        return False
    overlap = min(wall.t_range[1], other.t_range[1]) - max(wall.t_range[0], other.t_range[0])
    return overlap > 0.5 * (wall.t_range[1] - wall.t_range[0])


def _zipf_classes(pool: tuple[int, ...], n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` class ids drawn from ``pool`` with probability proportional to 1 / rank."""
    zipf = 1.0 / np.arange(1, len(pool) + 1)
    return np.asarray(pool, dtype=np.uint8)[rng.choice(len(pool), size=n, p=zipf / zipf.sum())]


def _count(per_m2: float, area: float, bounds: tuple[int, int], available: int) -> int:
    return min(int(np.clip(round(per_m2 * area), *bounds)), available)


def fit_space_labelling(
    scene: Scene, seed: int = 0, config: SpaceLabelConfig | None = None
) -> SpaceLabelling:
    """The labelling of space of ``scene`` for ``seed``, from its depth and poses only (module
    docstring)."""
    cfg = config or SpaceLabelConfig()
    check_seed(seed)
    where = require_depth(scene, "space labels need depth")
    points, normals = fuse_points(scene, cfg)
    if len(points) == 0:
        raise CSAInputError(where, "no frame has any depth: nothing to label")
    up = estimate_up(scene, normals, cfg)
    cam_h = float(
        np.median([np.asarray(f.pose, dtype=np.float64)[:3, 3] @ up for f in scene.frames])
    )
    facing = np.where(np.isfinite(normals).all(axis=1), np.nan_to_num(normals) @ up, 0.0)
    floor = _horizontal_plane(points, facing, up, cam_h - cfg.floor_below_camera, cfg)
    ceiling = _horizontal_plane(points, -facing, -up, -(cam_h + cfg.ceiling_above_camera), cfg)
    labelling = SpaceLabelling(up, floor, ceiling, config=cfg)
    free = labelling.structure(points) == 0
    labelling.walls = _find_walls(points[free], normals[free], up, cfg)
    rest = points[labelling.structure(points) == 0]

    # Furniture cells and object balls on the remaining surface (module docstring, step 5).
    area = len(rest) * cfg.voxel**2
    rng = [np.random.default_rng([int(seed), stream]) for stream in range(_STREAMS)]
    k = _count(cfg.furniture_per_m2, area, cfg.furniture, len(rest))
    labelling.furniture_seeds = rest[
        np.sort(rng[_FURNITURE].choice(len(rest), size=k, replace=False))
    ]
    labelling.furniture_classes = _zipf_classes(FURNITURE_CLASSES, k, rng[_FURNITURE])
    j = _count(cfg.objects_per_m2, area, cfg.objects, len(rest))
    labelling.object_seeds = rest[np.sort(rng[_OBJECTS].choice(len(rest), size=j, replace=False))]
    lo, hi = cfg.object_radius
    labelling.object_radii = np.exp(rng[_OBJECTS].uniform(np.log(lo), np.log(hi), size=j))
    labelling.object_classes = _zipf_classes(OBJECT_CLASSES, j, rng[_OBJECTS])
    return labelling


def label_frame(labelling: SpaceLabelling, frame: Frame, intr: Intrinsics) -> np.ndarray:
    """(H, W) uint8 NYU40 ids of a frame: the label of each pixel's backprojected measured
    depth; 0 where the frame has no depth."""
    world, valid = frame_points(frame, intr)
    out = np.zeros(valid.shape, dtype=np.uint8)
    out[valid] = labelling.label_points(world[valid])
    return out


def space_labels(
    scene: Scene, seed: int = 0, config: SpaceLabelConfig | None = None
) -> dict[str, np.ndarray]:
    """``{frame name: (H, W) uint8 NYU40 ids}`` for every frame of ``scene``, from the
    labelling of space :func:`fit_space_labelling` builds for ``seed``."""
    labelling = fit_space_labelling(scene, seed, config)
    return {f.name: label_frame(labelling, f, scene.intrinsics) for f in scene.frames}


def add_space_labels(
    scene: Scene, seed: int = 0, folder: str = NYU40_FOLDER, config: SpaceLabelConfig | None = None
) -> SpaceLabelling:
    """Write :func:`space_labels` into every frame of ``scene`` under ``folder`` (the ground
    truth ``label-nyu40`` by default), in place; returns the labelling."""
    labelling = fit_space_labelling(scene, seed, config)
    for f in scene.frames:
        f.labels[folder] = label_frame(labelling, f, scene.intrinsics)
    return labelling


def label_shares(scene: Scene, folder: str = NYU40_FOLDER) -> dict[int, float]:
    """Share of the labelled (non-zero) pixels of ``scene`` that each class id covers."""
    counts = np.zeros(256, dtype=np.int64)
    for f in scene.frames:
        counts += np.bincount(f.labels[folder].ravel(), minlength=256)
    total = counts[1:].sum()
    return (
        {int(c): float(counts[c] / total) for c in np.flatnonzero(counts[1:]) + 1} if total else {}
    )
