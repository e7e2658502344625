"""Rendering a fitted Semantic-NeRF: images, depth and pseudo-labels at any camera pose.

``views``: ``train`` / ``val`` / ``all`` are the scene's frames; ``novel`` are the paper's
interpolated viewpoints between consecutive training frames (slerp midpoint of the
rotations, mean of the translations). Training and novel views can be rendered from a
checkpoint alone (it stores the training poses); ``val`` and ``all`` need the scene.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from csa_core.atomic_io import atomic_dir
from csa_core.data import image_files as imf
from csa_core.data.camera import Intrinsics
from csa_core.data.label_images import save_preview
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.nerf.fit import image_rays
from csa_core.nerf.model import SemanticNerf

VIEWS = ("train", "val", "all", "novel")


@dataclass
class RenderedView:
    """One rendered camera: RGB uint8 (H, W, 3), z-depth float32 metres (H, W), NYU40 ids uint8
    (H, W) and the rendered probability of that class (H, W) float32 (``None`` without semantics)."""

    name: str
    pose: np.ndarray
    color: np.ndarray
    depth: np.ndarray
    labels: np.ndarray | None = None
    confidence: np.ndarray | None = None


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def interpolate_pose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The paper's novel viewpoint between two camera-to-world poses: slerp midpoint of the
    rotations (the normalised sum of sign-aligned quaternions), mean of the translations."""
    qa, qb = _quat_from_matrix(np.asarray(a)[:3, :3]), _quat_from_matrix(np.asarray(b)[:3, :3])
    if np.dot(qa, qb) < 0:
        qb = -qb
    pose = np.eye(4)
    pose[:3, :3] = _matrix_from_quat(qa + qb)
    pose[:3, 3] = 0.5 * (np.asarray(a)[:3, 3] + np.asarray(b)[:3, 3])
    return pose


def novel_view_poses(
    names: Sequence[str], poses: Sequence[np.ndarray]
) -> list[tuple[str, np.ndarray]]:
    """Novel views between consecutive training frames, named ``<a>_<b>`` after the pair."""
    return [
        (f"{names[i]}_{names[i + 1]}", interpolate_pose(poses[i], poses[i + 1]))
        for i in range(len(poses) - 1)
    ]


def view_poses(
    nerf: SemanticNerf, views: str = "train", scene: Scene | None = None
) -> list[tuple[str, np.ndarray]]:
    """``(name, pose)`` of the requested views; ``train``/``novel`` fall back to the checkpoint's poses."""
    if views not in VIEWS:
        raise CSAInputError("--views", f"unknown views {views!r} (choose from {', '.join(VIEWS)})")
    if views == "novel":
        if scene is not None:
            frames = scene.train_frames
            return novel_view_poses([f.name for f in frames], [f.pose for f in frames])
        return novel_view_poses(nerf.info.train_frames, list(nerf.info.train_poses))
    if scene is None:
        if views != "train":
            raise CSAInputError(
                "--scene",
                f"views '{views}' need the scene folder (the checkpoint stores training poses only)",
            )
        return list(zip(nerf.info.train_frames, list(nerf.info.train_poses), strict=True))
    return [(f.name, np.asarray(f.pose)) for f in scene.split(views)]


def render_image(
    nerf: SemanticNerf,
    pose: np.ndarray,
    intrinsics: Intrinsics | None = None,
    name: str = "",
    semantics: bool = True,
    sampler: str | None = None,
    appearance: int | None = None,
) -> RenderedView:
    """Render one camera (default: the training camera) at a camera-to-world ``pose``.
    ``appearance``: index of the training frame whose colour correction to apply (models fitted
    with ``appearance="affine"``); ``None`` renders the average appearance."""
    intr = intrinsics or nerf.info.intrinsics
    origins, dirs = image_rays(intr, pose, nerf.device)
    out = nerf.render_rays(
        origins, dirs, sampler=sampler, semantics=semantics, appearance=appearance
    )
    h, w = intr.height, intr.width
    color = (out["rgb"].clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).reshape(h, w, 3).cpu().numpy()
    depth = out["depth"].reshape(h, w).float().cpu().numpy()
    view = RenderedView(
        name=name, pose=np.asarray(pose, dtype=np.float64), color=color, depth=depth
    )
    if semantics:
        conf, cls = out["semantics"].max(dim=-1)
        view.labels = (cls + 1).to(torch.uint8).reshape(h, w).cpu().numpy()
        view.confidence = conf.reshape(h, w).float().cpu().numpy()
    return view


def render_views(
    nerf: SemanticNerf,
    scene: Scene | None = None,
    views: str = "train",
    semantics: bool = True,
    sampler: str | None = None,
    progress: bool = False,
) -> list[RenderedView]:
    """Render the ``views`` (train, val, all or novel) of a scene at the checkpoint's camera."""
    poses = view_poses(nerf, views, scene)
    intr = scene.intrinsics if scene is not None else nerf.info.intrinsics
    it = poses
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(poses, desc=f"render {views}", unit="view", dynamic_ncols=True)
    return [
        render_image(nerf, pose, intr, name=name, semantics=semantics, sampler=sampler)
        for name, pose in it
    ]


def render_pseudo_labels(
    nerf: SemanticNerf, scene: Scene | None = None, views: str = "train", sampler: str | None = None
) -> dict[str, np.ndarray]:
    """NYU40 pseudo-labels ``{frame name: (H, W) uint8}`` rendered at the ``views``."""
    return {
        v.name: v.labels for v in render_views(nerf, scene, views, semantics=True, sampler=sampler)
    }


def write_rendered_views(
    views: Sequence[RenderedView],
    out: str | Path,
    intrinsics: Intrinsics,
    overwrite: bool = False,
    previews: bool = True,
) -> Path:
    """Write rendered views as a scene folder (atomically): ``color/`` (PNG), ``depth/`` (uint16
    mm), ``label-nyu40/`` (uint8 NYU40), ``pose/``, ``intrinsic/`` and ``preview/`` (colour |
    labels | overlay | legend), so the output can be read back with ``read_scene``."""
    out = Path(out)
    K = np.eye(4)
    K[:3, :3] = intrinsics.matrix()
    with atomic_dir(out, overwrite=overwrite) as tmp:
        for sub in ("color", "depth", "pose", "intrinsic"):
            (tmp / sub).mkdir()
        imf.write_matrix(tmp / "intrinsic" / "intrinsic_color.txt", K)
        imf.write_matrix(tmp / "intrinsic" / "intrinsic_depth.txt", K)
        for v in views:
            imf.write_color(tmp / "color" / f"{v.name}.png", v.color)
            imf.write_depth(tmp / "depth" / f"{v.name}.png", v.depth)
            imf.write_matrix(tmp / "pose" / f"{v.name}.txt", v.pose)
            if v.labels is not None:
                (tmp / NYU40_FOLDER).mkdir(exist_ok=True)
                imf.write_labels(tmp / NYU40_FOLDER / f"{v.name}.png", v.labels)
                if previews:
                    (tmp / "preview").mkdir(exist_ok=True)
                    save_preview(tmp / "preview" / f"{v.name}.jpg", v.color, v.labels)
    return out
