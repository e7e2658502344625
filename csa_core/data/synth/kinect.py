"""Kinect-like captures of clean scenes: the hard variant of a room.

A synthetic room has exact depth and exact labels. A real RGB-D sensor and a real per-frame
segmentation network give neither. :func:`degrade_scene` turns a clean scene into what a
Kinect v1 and a network would deliver:

- **depth noise** growing with range, sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m along the ray
  (the axial model of Nguyen, Izadi and Lovell, 3DIMPVT 2012), plus their lateral jitter of
  about 0.8 px at 640x480;
- **holes** (depth 0) where a Kinect measures nothing: the projector's shadow beside near
  objects and a band at every depth discontinuity, beyond the sensor's range, on a share of
  dark surfaces (low colour intensity: too little infrared comes back) and of surfaces seen at
  grazing angles (large angle between the view ray and the normal estimated from depth);
- **colour noise**;
- **label errors** in a ``label-noisy`` folder: *systematic* ones, the same in every view that
  sees a region from one side (a network that mistakes one sofa's back for a bed does so in
  every frame), and the per-frame ones of :mod:`csa_core.data.label_noise`.

The ground-truth folder stays clean for scoring. Every random choice derives from ``seed`` and
the frame's name, and region-wise choices from hashes of world coordinates, so the output
depends only on the inputs.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from csa_core.data.camera import Intrinsics
from csa_core.data.depth_edges import discontinuity_band
from csa_core.data.label_noise import LabelNoiseConfig, corrupt_labels
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene, require_depth
from csa_core.data.synth.noise import hash01, value_noise3
from csa_core.errors import CSAInputError, check_seed

NOISY_FOLDER = "label-noisy"
REFERENCE_WIDTH = 640  # pixel sizes in the config are given at the Kinect's 640x480

# Random streams per frame, and hash streams per region (one role each).
_DEPTH, _LATERAL, _COLOR, _LABELS = range(4)
_DARK, _GRAZING, _SYSTEMATIC, _WRONG_CLASS = range(4)


@dataclass
class KinectConfig:
    """How a clean scene is degraded. Lengths in metres; pixel sizes at 640 px width, scaled
    with the scene's width; shares are fractions of the surface concerned."""

    # Axial depth noise sigma(z) = axial_base + axial_quadratic * (z - axial_offset)^2
    # (Nguyen et al. 2012, fitted on a Kinect v1 between 0.5 and 3 m).
    axial_base: float = 0.0012
    axial_quadratic: float = 0.0019
    axial_offset: float = 0.4
    lateral_px: float = 0.8  # std of the lateral jitter (Nguyen et al. 2012: 0.8 px, any range)
    min_range: float = 0.5  # nearer surfaces read 0 (Kinect v1 near limit)
    max_range: float = 5.0  # farther surfaces read 0 (where Kinect v1 depth gives out)
    baseline: float = 0.075  # projector to camera (Kinect v1); shadows fall left of near objects
    edge_jump: float = 0.05  # a discontinuity: neighbours' depths differ by this share of depth
    edge_band_px: float = 2.0  # width of the invalid band on each side of a discontinuity
    dark_luma: float = 40.0  # "dark": Rec. 601 luma of the clean colour below this (0-255)
    dark_share: float = 0.5  # share of dark surface that returns no depth
    grazing_deg: float = 75.0  # "grazing": angle between view ray and surface normal above this
    grazing_share: float = 0.5  # share of grazing surface (per frame) that returns no depth
    hole_cell: float = 0.2  # holes on dark and grazing surfaces come in patches of this size
    color_noise: float = 2.0  # std of the colour noise, 8-bit units
    region_size: float = 0.5  # systematic label errors: edge of the cells they are decided on
    systematic_share: float = 0.15  # share of (cell, side, class) regions that get a wrong class
    frame_noise: LabelNoiseConfig | None = field(default_factory=LabelNoiseConfig)  # None: off

    def __post_init__(self) -> None:
        positive = ("axial_offset", "max_range", "hole_cell", "region_size")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"KinectConfig: {name} must be > 0, got {getattr(self, name)}")
        non_negative = (
            "axial_base", "axial_quadratic", "lateral_px", "min_range", "baseline", "edge_jump",
            "edge_band_px", "dark_luma", "color_noise",
        )  # fmt: skip
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ValueError(f"KinectConfig: {name} must be >= 0, got {getattr(self, name)}")
        for name in ("dark_share", "grazing_share", "systematic_share"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(
                    f"KinectConfig: {name} must be in [0, 1], got {getattr(self, name)}"
                )
        if not 0 < self.grazing_deg <= 90:
            raise ValueError(
                f"KinectConfig: grazing_deg must be in (0, 90], got {self.grazing_deg}"
            )
        if self.min_range >= self.max_range:
            raise ValueError("KinectConfig: min_range must be below max_range")


def axial_sigma(depth: np.ndarray, config: KinectConfig | None = None) -> np.ndarray:
    """Standard deviation (m) of the depth noise along the ray at z-depth ``depth`` (m)."""
    cfg = config or KinectConfig()
    z = np.asarray(depth, dtype=np.float64)
    return cfg.axial_base + cfg.axial_quadratic * (z - cfg.axial_offset) ** 2


def _frame_rng(seed: int, name: str, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(name.encode()), stream])


def _cell_hash(
    points: np.ndarray, size: float, seed: int, stream: int, *extra: np.ndarray | int
) -> np.ndarray:
    """Uniform [0, 1) value of the cell of ``size`` metres that each world point (..., 3) falls
    in, mixed with ``extra`` integer keys: the same for every view of that cell. Cell walls are
    warped by smooth noise (up to a quarter cell), so regions are blobs rather than cubes."""
    key = int(np.random.SeedSequence([seed, stream]).generate_state(1)[0])
    q = points / size
    warp = np.stack([value_noise3(q, seed=key + 1 + k) for k in range(3)], axis=-1)
    cells = np.floor(q + 0.5 * (warp - 0.5))
    return hash01(cells[..., 0], cells[..., 1], cells[..., 2], *extra, seed=key)


def _camera_points(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (H, W, 3) of a z-depth map."""
    u, v = np.meshgrid(
        np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64)
    )
    z = depth.astype(np.float64)
    return np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=-1)


def _tangent(p: np.ndarray, axis: int) -> np.ndarray:
    """Derivative of camera points along an image axis: the one-sided difference that changes
    depth least, so that a pixel on a crease or beside a jump takes its own surface's slope."""
    diff = np.diff(p, axis=axis)
    pad = [(0, 0)] * p.ndim
    pad[axis] = (0, 1)
    forward = np.pad(diff, pad, constant_values=np.nan)
    pad[axis] = (1, 0)
    backward = np.pad(diff, pad, constant_values=np.nan)
    fz = np.nan_to_num(np.abs(forward[..., 2:]), nan=np.inf)
    bz = np.nan_to_num(np.abs(backward[..., 2:]), nan=np.inf)
    return np.where(fz <= bz, forward, backward)


def _normals(points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) from the image-space derivatives of camera points, turned to face
    the camera; NaN where a pixel has no neighbour with depth along an axis."""
    p = np.where(valid[..., None], points, np.nan)
    n = np.cross(_tangent(p, 1), _tangent(p, 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        flip = np.sum(n * points, axis=-1) > 0
    n[flip] *= -1.0
    return n


def _projector_shadow(
    depth: np.ndarray, valid: np.ndarray, fx: float, baseline: float
) -> np.ndarray:
    """Pixels the projector cannot see. The projector sits ``baseline`` to the camera's right; a
    pixel at column u and depth z appears at u - fx * baseline / z in its image, and is hidden
    when a pixel to its right appears farther left there (it is in front along that ray)."""
    if baseline <= 0:
        return np.zeros_like(valid)
    h, w = depth.shape
    u = np.arange(w, dtype=np.float64)[None, :]
    with np.errstate(divide="ignore"):
        seen_at = np.where(valid, u - fx * baseline / np.where(valid, depth, 1.0), np.inf)
    # Minimum over the columns strictly to the right of each pixel.
    right = np.minimum.accumulate(seen_at[:, ::-1], axis=1)[:, ::-1]
    right = np.concatenate([right[:, 1:], np.full((h, 1), np.inf)], axis=1)
    return valid & (right < seen_at)


def mix_depth_edges(
    depth: np.ndarray, rng: np.random.Generator, share: float = 0.5, rel_jump: float = 0.05
) -> np.ndarray:
    """Flying pixels, as a time-of-flight sensor gives them: a pixel beside a depth jump collects
    light from both surfaces and reads a depth between them. ``share`` of the pixels on either
    side of every jump larger than ``rel_jump`` times the nearer depth read a depth drawn
    uniformly between 10% and 90% of the way from the nearest to the farthest measured depth of
    their 3x3 neighbourhood; other pixels keep theirs. Returns a new float32 array (0 stays "not
    measured")."""
    if not 0 <= share <= 1:
        raise ValueError(f"mix_depth_edges: share must be in [0, 1], got {share}")
    d = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    edge = discontinuity_band(d, valid, rel_jump, 1.0)
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(np.where(valid, d, np.inf).astype(np.float32), kernel)
    far = cv2.dilate(np.where(valid, d, 0.0).astype(np.float32), kernel)
    pick = edge & (rng.random(d.shape) < share)
    alpha = rng.uniform(0.1, 0.9, d.shape).astype(np.float32)
    out = np.where(valid, d, 0.0).astype(np.float32)
    out[pick] = (near + alpha * (far - near))[pick]
    return out


def _scene_classes(scene: Scene, folder: str) -> np.ndarray:
    counts = np.zeros(256, dtype=np.int64)
    for f in scene.frames:
        counts += np.bincount(f.labels[folder].ravel(), minlength=256)
    return np.flatnonzero(counts[1:]) + 1


def _systematic_labels(
    labels: np.ndarray,
    world: np.ndarray,
    side: np.ndarray,
    known: np.ndarray,
    classes: np.ndarray,
    cfg: KinectConfig,
    seed: int,
) -> np.ndarray:
    """Relabel the pixels of a share of regions; a region is (cell of ``region_size``, the side
    it is seen from, its true class), and its wrong class is fixed by the same hashes."""
    out = labels.copy()
    ok = known & (labels > 0)
    if classes.size < 2 or cfg.systematic_share <= 0 or not ok.any():
        return out
    lab = labels[ok].astype(np.int64)
    key = side[ok] * 64 + lab
    p = world[ok]
    chosen = _cell_hash(p, cfg.region_size, seed, _SYSTEMATIC, key) < cfg.systematic_share
    # The k-th of the scene's other classes, k fixed by the region.
    pick = _cell_hash(p, cfg.region_size, seed, _WRONG_CLASS, key)
    k = np.minimum((pick * (classes.size - 1)).astype(np.int64), classes.size - 2)
    pos = np.searchsorted(classes, lab)  # every known label is one of the scene's classes
    wrong = classes[k + (k >= pos)]
    lab = np.where(chosen, wrong, lab)
    out[ok] = lab.astype(np.uint8)
    return out


def degrade_frame(
    frame: Frame,
    intrinsics: Intrinsics,
    config: KinectConfig,
    seed: int,
    classes: np.ndarray,
    source: str | None = NYU40_FOLDER,
    target: str = NOISY_FOLDER,
) -> Frame:
    """One frame as the sensor and a network would see it (see the module's docstring);
    ``classes``: the scene's label ids, the wrong classes of systematic errors."""
    cfg = config
    if frame.depth is None:
        raise CSAInputError(f"frame {frame.name}", "a Kinect-like capture needs depth")
    depth = np.asarray(frame.depth, dtype=np.float64)
    h, w = intrinsics.height, intrinsics.width
    for what, image in [("depth", depth), ("colour", frame.color), *frame.labels.items()]:
        if image.shape[:2] != (h, w):
            raise CSAInputError(
                f"frame {frame.name}",
                f"{what} is {image.shape[1]}x{image.shape[0]}, the scene's camera {w}x{h}",
            )
    valid = np.isfinite(depth) & (depth > 0)
    depth = np.where(valid, depth, 0.0)
    scale = w / REFERENCE_WIDTH
    pose = np.asarray(frame.pose, dtype=np.float64)
    cam = _camera_points(depth, intrinsics)
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    normals = _normals(cam, valid)

    # Holes decided on the clean geometry.
    holes = ~valid | (depth < cfg.min_range) | (depth > cfg.max_range)
    holes |= _projector_shadow(depth, valid, intrinsics.fx, cfg.baseline)
    holes |= discontinuity_band(depth, valid, cfg.edge_jump, cfg.edge_band_px * scale)
    color = frame.color.astype(np.float64)
    luma = 0.299 * color[..., 0] + 0.587 * color[..., 1] + 0.114 * color[..., 2]
    if cfg.dark_share > 0:
        dark = valid & (luma < cfg.dark_luma)
        holes |= dark & (_cell_hash(world, cfg.hole_cell, seed, _DARK) < cfg.dark_share)
    if cfg.grazing_share > 0:
        with np.errstate(invalid="ignore"):
            cos = -np.sum(normals * cam, axis=-1) / np.maximum(np.linalg.norm(cam, axis=-1), 1e-12)
            grazing = valid & (cos < np.cos(np.radians(cfg.grazing_deg)))
        per_frame = zlib.crc32(frame.name.encode()) & 0x7FFFFFFF
        patch = _cell_hash(world, cfg.hole_cell, seed, _GRAZING, per_frame)
        holes |= grazing & (patch < cfg.grazing_share)

    # Lateral jitter: each pixel reads the depth of a pixel displaced by a rounded normal offset.
    noisy = depth
    if cfg.lateral_px > 0:
        rng = _frame_rng(seed, frame.name, _LATERAL)
        s = cfg.lateral_px * scale
        yy, xx = np.mgrid[0:h, 0:w]
        sy = np.clip(np.rint(yy + rng.normal(0.0, s, (h, w))), 0, h - 1).astype(np.int64)
        sx = np.clip(np.rint(xx + rng.normal(0.0, s, (h, w))), 0, w - 1).astype(np.int64)
        noisy = depth[sy, sx]
        holes |= holes[sy, sx]
    noise = _frame_rng(seed, frame.name, _DEPTH).standard_normal((h, w))
    noisy = noisy + noise * axial_sigma(noisy, cfg)
    holes |= noisy <= 0
    out_depth = np.where(holes, 0.0, noisy).astype(np.float32)

    out_color = frame.color
    if cfg.color_noise > 0:
        jitter = _frame_rng(seed, frame.name, _COLOR).normal(0.0, cfg.color_noise, color.shape)
        out_color = np.clip(np.rint(color + jitter), 0, 255).astype(np.uint8)

    labels = {k: v.copy() for k, v in frame.labels.items()}
    if source is not None:
        # The side a surface is seen from: the dominant world axis of its camera-facing normal.
        n_world = normals @ pose[:3, :3].T
        axis = np.nan_to_num(np.abs(n_world), nan=0.0).argmax(axis=-1)
        negative = np.take_along_axis(n_world, axis[..., None], axis=-1)[..., 0] < 0
        side = axis * 2 + negative
        known = valid & np.isfinite(normals).all(axis=-1)
        noisy_labels = _systematic_labels(
            frame.labels[source], world, side, known, classes, cfg, seed
        )
        if cfg.frame_noise is not None:
            rng = _frame_rng(seed, frame.name, _LABELS)
            noisy_labels = corrupt_labels(noisy_labels, rng, cfg.frame_noise)
        labels[target] = noisy_labels
    return Frame(
        name=frame.name, color=out_color, pose=frame.pose.copy(), depth=out_depth, labels=labels
    )


def degrade_scene(
    scene: Scene,
    seed: int = 0,
    config: KinectConfig | None = None,
    source: str | None = NYU40_FOLDER,
    target: str = NOISY_FOLDER,
) -> Scene:
    """A Kinect-like copy of ``scene`` (the input is not changed): noisy depth with holes, noisy
    colour, and ``target`` labels made from ``source`` with systematic and per-frame errors
    (``source=None``: colour and depth only). Other label folders are copied unchanged."""
    cfg = config or KinectConfig()
    seed = check_seed(seed)
    where = require_depth(scene, "a Kinect-like capture needs depth")
    classes = np.zeros(0, dtype=np.int64)
    if source is not None:
        if source == target:
            raise CSAInputError("--target", f"must differ from the source labels {source!r}")
        missing = [f.name for f in scene.frames if source not in f.labels]
        if missing:
            raise CSAInputError(
                where, f"no label folder {source!r} for frame(s) {', '.join(missing[:5])}"
            )
        classes = _scene_classes(scene, source)
    frames = [
        degrade_frame(f, scene.intrinsics, cfg, seed, classes, source, target) for f in scene.frames
    ]
    return Scene(
        name=scene.name, intrinsics=scene.intrinsics, frames=frames, skipped=list(scene.skipped)
    )


def degrade_scene_folder(
    src: str | Path,
    dst: str | Path,
    seed: int = 0,
    config: KinectConfig | None = None,
    source: str | None = NYU40_FOLDER,
    target: str = NOISY_FOLDER,
    overwrite: bool = False,
) -> Scene:
    """Read the scene folder ``src``, degrade it (:func:`degrade_scene`) and write it to ``dst``
    atomically (colour as PNG). Returns the degraded scene."""
    from csa_core.data.scene_io import read_scene, write_scene

    dst = Path(dst)
    if Path(src).resolve() == dst.resolve():
        raise CSAInputError(dst, "output must differ from the input scene folder")
    if dst.exists() and not overwrite:
        raise CSAInputError(dst, "output already exists (pass --overwrite to replace it)")
    scene = read_scene(src, labels="all")
    out = degrade_scene(scene, seed, config, source, target)
    out.name = dst.name
    write_scene(out, dst, overwrite=overwrite)
    out.root = dst
    return out
