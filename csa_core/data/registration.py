"""Colour cameras that are not the depth camera: register depth to colour before fitting.

A NeRF treats every pixel as a ray of the frame's camera. Kinect v1 data such as 7-Scenes
stores raw colour and raw depth: the pose and the published intrinsics (fx = fy = 585) belong
to the depth camera, while the colour camera sits a few centimetres beside it with a wider
field of view (fx ~ 525). Reading the colour image with the depth camera's rays shifts and
scales it by up to ~30 px (640 px wide) near the image border, differently in every view, so
the colour of one surface point disagrees between views. This module moves a scene to its
colour camera: poses become colour-camera poses, intrinsics the colour camera's, and the depth
is splatted into the colour image with a z-buffer (pixels that no depth point reaches become
0, "not measured"). Colour, which drives the photometric loss, is left untouched.

``color_consistency_rms`` measures how well a camera model explains the data without any fit
(colour disagreement of measured 3D points seen by two frames), and ``estimate_color_camera``
searches the model that minimises it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from csa_core.data.camera import Intrinsics, backproject
from csa_core.data.scene import Frame, Scene


@dataclass(frozen=True)
class ColorCamera:
    """The colour camera of an RGB-D rig, rigidly attached to the depth camera (axes parallel).

    ``intrinsics`` at any resolution (scaled to the scene's working size); ``offset`` the
    colour camera's centre in the depth camera frame, metres (OpenCV axes).
    """

    intrinsics: Intrinsics
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def at_size(self, width: int, height: int) -> Intrinsics:
        return self.intrinsics.scaled(width, height)

    def to_dict(self) -> dict:
        return {"intrinsics": self.intrinsics.to_dict(), "offset": list(self.offset)}


# Estimated on 7-Scenes "red kitchen" (100 frames, 320x240) with ``estimate_color_camera``
# started from the usual Kinect v1 colour defaults (fx = fy = 525, centre 320, 240, 2.5 cm
# baseline): multi-view colour RMS 24.9 (depth camera) -> 16.6 (8-bit),
# benchmarks/results/components.md "7-Scenes red kitchen".
# In 640x480 pixels, pixel-edge convention of ``Intrinsics``.
KINECT_V1_COLOR = ColorCamera(Intrinsics(523.0, 523.0, 319.5, 235.0, 640, 480), (0.025, 0.0, 0.0))


def color_pose(depth_pose: np.ndarray, camera: ColorCamera) -> np.ndarray:
    """Camera-to-world pose of the colour camera from the depth camera's pose."""
    pose = np.array(depth_pose, dtype=np.float64, copy=True)
    pose[:3, 3] = pose[:3, :3] @ np.asarray(camera.offset, dtype=np.float64) + pose[:3, 3]
    return pose


def register_depth(
    depth: np.ndarray, depth_intr: Intrinsics, color_intr: Intrinsics, offset: Sequence[float]
) -> np.ndarray:
    """Splat a depth image of the depth camera into the colour camera (nearest pixel, the
    closest point wins); returns z-depth in the colour camera, 0 where no point landed."""
    out = np.full((color_intr.height, color_intr.width), np.inf, dtype=np.float64)
    pts = backproject(depth.astype(np.float64), depth_intr, np.eye(4))[depth > 0]
    pts = pts - np.asarray(offset, dtype=np.float64)
    z = pts[:, 2]
    ok = z > 1e-6
    pts, z = pts[ok], z[ok]
    u = np.round(pts[:, 0] / z * color_intr.fx + color_intr.cx).astype(np.int64)
    v = np.round(pts[:, 1] / z * color_intr.fy + color_intr.cy).astype(np.int64)
    inside = (u >= 0) & (u < color_intr.width) & (v >= 0) & (v < color_intr.height)
    np.minimum.at(out.reshape(-1), (v * color_intr.width + u)[inside], z[inside])
    out[~np.isfinite(out)] = 0.0
    return out.astype(np.float32)


def to_color_camera(scene: Scene, camera: ColorCamera) -> Scene:
    """The scene seen from its colour camera: colour-camera poses and intrinsics, depth
    registered to colour. ``scene`` must hold depth in the depth camera (``scene.intrinsics``)."""
    cintr = camera.at_size(scene.intrinsics.width, scene.intrinsics.height)
    frames = []
    for f in scene.frames:
        depth = None
        if f.depth is not None:
            depth = register_depth(f.depth, scene.intrinsics, cintr, camera.offset)
        frames.append(
            Frame(
                name=f.name,
                color=f.color,
                pose=color_pose(f.pose, camera),
                depth=depth,
                labels=dict(f.labels),
            )
        )
    return replace(scene, intrinsics=cintr, frames=frames)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    m = cv2.remap(
        img.astype(np.float32),
        u.astype(np.float32).reshape(1, -1),
        v.astype(np.float32).reshape(1, -1),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return m.reshape(-1, img.shape[-1]).astype(np.float64)


class _CoVisiblePoints:
    """Measured 3D points (world) of frame pairs, kept where both depth maps agree."""

    def __init__(self, scene: Scene, pairs: Sequence[tuple[int, int]], max_points: int, seed: int):
        rng = np.random.default_rng(seed)
        k = scene.intrinsics
        self.items: list[tuple[Frame, Frame, np.ndarray]] = []
        for i, j in pairs:
            a, b = scene.frames[i], scene.frames[j]
            if a.depth is None or b.depth is None:
                continue
            x = backproject(a.depth.astype(np.float64), k, np.asarray(a.pose))[a.depth > 0]
            inv = np.linalg.inv(np.asarray(b.pose, dtype=np.float64))
            q = x @ inv[:3, :3].T + inv[:3, 3]
            z = np.maximum(q[:, 2], 1e-6)
            u = np.round(q[:, 0] / z * k.fx + k.cx).astype(np.int64)
            v = np.round(q[:, 1] / z * k.fy + k.cy).astype(np.int64)
            inside = (q[:, 2] > 0.1) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
            d = np.zeros(len(x))
            d[inside] = b.depth[v[inside], u[inside]]
            seen = inside & (np.abs(d - q[:, 2]) < 0.03 + 0.02 * q[:, 2])
            x = x[seen]
            if len(x) > max_points:
                x = x[rng.choice(len(x), max_points, replace=False)]
            if len(x):
                self.items.append((a, b, x))


def _colour_of(frame: Frame, points: np.ndarray, cam: ColorCamera, cintr: Intrinsics):
    pose = color_pose(frame.pose, cam)
    inv = np.linalg.inv(pose)
    q = points @ inv[:3, :3].T + inv[:3, 3]
    z = np.maximum(q[:, 2], 1e-6)
    u, v = q[:, 0] / z * cintr.fx + cintr.cx, q[:, 1] / z * cintr.fy + cintr.cy
    inside = (u >= 0) & (u <= cintr.width - 1) & (v >= 0) & (v <= cintr.height - 1)
    return _bilinear(frame.color, u, v), (q[:, 2] > 0.1) & inside


def default_pairs(n: int) -> list[tuple[int, int]]:
    """Frame pairs for the consistency measure: neighbours and frames three apart."""
    return [(i, i + 1) for i in range(0, n - 1, 3)] + [(i, i + 3) for i in range(0, n - 3, 7)]


def color_consistency_rms(
    scene: Scene,
    camera: ColorCamera | None,
    pairs: Sequence[tuple[int, int]] | None = None,
    max_points: int = 4000,
    seed: int = 0,
    _points: _CoVisiblePoints | None = None,
) -> float:
    """RMS (8-bit units) of the colour difference between two frames at measured 3D points that
    both see, colour read through ``camera`` (``None``: the depth camera itself). Lower means
    the camera model registers colour to depth and poses better. ``scene`` as loaded (depth
    camera)."""
    if camera is None:
        camera = ColorCamera(scene.intrinsics)
    pts = _points or _CoVisiblePoints(
        scene, default_pairs(len(scene.frames)) if pairs is None else pairs, max_points, seed
    )
    cintr = camera.at_size(scene.intrinsics.width, scene.intrinsics.height)
    sq = []
    for a, b, x in pts.items:
        ca, oka = _colour_of(a, x, camera, cintr)
        cb, okb = _colour_of(b, x, camera, cintr)
        ok = oka & okb
        sq.append(((ca[ok] - cb[ok]) ** 2).mean(axis=1))
    if not sq or not sum(len(s) for s in sq):
        return float("nan")
    return float(np.sqrt(np.concatenate(sq).mean()))


def estimate_color_camera(
    scene: Scene,
    init: ColorCamera,
    steps: tuple[float, float, float, float] = (8.0, 4.0, 4.0, 0.01),
    rounds: int = 4,
    max_points: int = 4000,
) -> tuple[ColorCamera, float]:
    """Coordinate descent on (focal, cx, cy, x offset) of ``init`` (fx = fy kept equal; steps in
    the units of ``init.intrinsics`` and metres, halved every round) minimising
    :func:`color_consistency_rms`. Returns the camera and its RMS."""
    pts = _CoVisiblePoints(scene, default_pairs(len(scene.frames)), max_points, 0)

    def make(p: list[float]) -> ColorCamera:
        k = init.intrinsics
        return ColorCamera(
            Intrinsics(p[0], p[0], p[1], p[2], k.width, k.height),
            (p[3], init.offset[1], init.offset[2]),
        )

    def cost(p: list[float]) -> float:
        return color_consistency_rms(scene, make(p), _points=pts)

    k = init.intrinsics
    best = [k.fx, k.cx, k.cy, init.offset[0]]
    best_cost = cost(best)
    step = list(steps)
    for _ in range(rounds):
        for i in range(4):
            for sign in (-1.0, 1.0):
                while True:
                    cand = list(best)
                    cand[i] += sign * step[i]
                    c = cost(cand)
                    if c < best_cost - 1e-4:
                        best, best_cost = cand, c
                    else:
                        break
        step = [s / 2 for s in step]
    return make(best), best_cost
