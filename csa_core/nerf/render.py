"""Rendering a fitted Semantic-NeRF: images, depth and pseudo-labels at any camera pose.

``views``: ``train`` / ``val`` / ``all`` are the scene's frames; ``novel`` are the paper's
interpolated viewpoints between consecutive training frames (slerp midpoint of the
rotations, mean of the translations). Training and novel views can be rendered from a
checkpoint alone (it stores the training poses); ``val`` and ``all`` need the scene.

``unseen_unknown`` (default: the config's ``render_unseen_unknown``, off): a pixel whose
surface point (its measured depth, else the rendered depth) no training camera sees (with
``NerfConfig.observed_resolution`` > 0: that no training view measured,
``csa_core/nerf/visibility.py``, for pixels with measured depth only), or
whose ray renders no surface at all, gets label 0
(``UNKNOWN``: what the voxel map answers there; ignored by the segmentation loss, a miss in
the scores) and confidence 0.
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
from csa_core.data.nyu40 import UNKNOWN
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.nerf.model import SemanticNerf, render_chunk
from csa_core.nerf.rays import image_rays

VIEWS = ("train", "val", "all", "novel")


@dataclass
class RenderedView:
    """One rendered camera: RGB uint8 (H, W, 3) (``None`` when rendered without colour),
    z-depth float32 metres (H, W), NYU40 ids uint8 (H, W) and the rendered probability of that
    class (H, W) float32 (``None`` without semantics)."""

    name: str
    pose: np.ndarray
    color: np.ndarray | None
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
    """``(name, pose)`` of the requested views; ``train``/``novel`` fall back to the checkpoint's
    poses."""
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
                f"views '{views}' need the scene folder "
                "(the checkpoint stores training poses only)",
            )
        return list(zip(nerf.info.train_frames, list(nerf.info.train_poses), strict=True))
    return [(f.name, np.asarray(f.pose)) for f in scene.split(views)]


def check_scene_matches(nerf: SemanticNerf, scene: Scene, where: str | Path) -> None:
    """Refuse to render ``scene``'s views with a model fitted to another scene, naming ``where``:
    the scene's camera must be the model's, and the frames of the scene that the model was
    fitted to must have the poses it was fitted at (a scene holding none of them is another
    scene; one holding them at other poses too)."""
    a, b = scene.intrinsics, nerf.info.intrinsics
    if (a.width, a.height) != (b.width, b.height) or not np.allclose(
        [a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=1e-6, atol=1e-6
    ):
        raise CSAInputError(
            where,
            f"its camera (fx {a.fx:g}, fy {a.fy:g}, cx {a.cx:g}, cy {a.cy:g} "
            f"at {a.width}x{a.height}) is not the "
            f"checkpoint's (fx {b.fx:g}, fy {b.fy:g}, cx {b.cx:g}, cy {b.cy:g}): "
            "a checkpoint of another scene?",
        )
    fitted = dict(zip(nerf.info.train_frames, nerf.info.train_poses, strict=True))
    common = [f for f in scene.frames if f.name in fitted]
    if not common:
        raise CSAInputError(
            where,
            f"none of its frames is one the checkpoint was fitted to (scene '{nerf.info.name}', "
            f"frames {', '.join(nerf.info.train_frames[:3])}, ...): a checkpoint of another scene?",
        )
    for f in common:
        if not np.allclose(np.asarray(f.pose, dtype=np.float64), fitted[f.name], rtol=0, atol=1e-4):
            raise CSAInputError(
                where,
                f"frame {f.name} has another pose than the checkpoint was fitted to "
                f"(scene '{nerf.info.name}'): a checkpoint of another scene?",
            )


def seen_surface(
    nerf: SemanticNerf,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    out: dict[str, torch.Tensor],
    depth: torch.Tensor | None = None,
) -> torch.Tensor:
    """Whether each ray's surface point was seen in training, (R,) bool: it lies in a cell
    where a training view measured a surface (``SemanticNerf.observed``, visibility.py, when
    the model has those cells), or else inside the image of at least one training camera
    (``SemanticNerf.seen_by_training_cameras``; the image reaches half a pixel beyond the
    outermost pixel centres, so the margin is about one pixel). The point is at the
    measured ``depth`` where there is one, else at the rendered depth (``out``'s depth over
    its opacity); rays with neither (nothing rendered) count as unseen. With the cells, only
    rays with a measured depth are tested; rays without one (depth holes, views without
    depth) count as seen where they render a surface: the cells hold measured surfaces, a
    surface the sensor never returns (dark, shiny) is in no cell although every view saw
    it, and a rendered depth is not precise enough to test against a cell."""
    opacity = out["opacity"]
    t = out["depth"] / opacity.clamp_min(1e-10)
    measured = torch.zeros_like(opacity, dtype=torch.bool)
    if depth is not None:
        measured = depth > 0
        t = torch.where(measured, depth, t)
    found = (opacity > 0) | measured
    tested = measured if nerf.observed is not None and nerf.observed.marked else found
    intr = nerf.info.intrinsics
    margin = 1.0 / min(intr.width, intr.height)
    seen = found & ~tested
    points = origins[tested] + dirs[tested] * t[tested, None]
    seen[tested] = nerf.seen_surface_points(points, margin=margin)
    return seen


def _view_from_output(
    out: dict[str, torch.Tensor],
    intr: Intrinsics,
    pose: np.ndarray,
    name: str,
    known: torch.Tensor | None = None,
) -> RenderedView:
    h, w = intr.height, intr.width
    if "rgb" in out:
        rgb = (out["rgb"].clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)
        color = rgb.reshape(h, w, 3).cpu().numpy()
    else:
        color = None
    depth = out["depth"].reshape(h, w).float().cpu().numpy()
    view = RenderedView(
        name=name, pose=np.asarray(pose, dtype=np.float64), color=color, depth=depth
    )
    if "semantics" in out:
        conf, cls = out["semantics"].max(dim=-1)
        cls = cls + 1
        if known is not None:
            cls = torch.where(known, cls, torch.full_like(cls, UNKNOWN))
            conf = torch.where(known, conf, torch.zeros_like(conf))
        view.labels = cls.to(torch.uint8).reshape(h, w).cpu().numpy()
        view.confidence = conf.reshape(h, w).float().cpu().numpy()
    return view


def render_image(
    nerf: SemanticNerf,
    pose: np.ndarray,
    intrinsics: Intrinsics | None = None,
    name: str = "",
    semantics: bool = True,
    sampler: str | None = None,
    appearance: int | None = None,
    depth: np.ndarray | None = None,
    color: bool = True,
    unseen_unknown: bool | None = None,
) -> RenderedView:
    """Render one camera (default: the training camera) at a camera-to-world ``pose``.
    ``appearance``: index of the training frame whose colour correction to apply (models fitted
    with ``appearance="affine"``); ``None`` renders the average appearance. ``depth``: the
    view's measured depth (H, W) metres, 0 = none; the config decides whether samples go
    around it (``SamplerConfig.render_depth_guided``). Without ``color``, ``color`` is ``None``.
    ``unseen_unknown``: see the module's description."""
    return render_frames(
        nerf,
        [(name, pose)],
        intrinsics,
        depths=None if depth is None else [depth],
        semantics=semantics,
        sampler=sampler,
        appearance=appearance,
        color=color,
        unseen_unknown=unseen_unknown,
    )[0]


def render_frames(
    nerf: SemanticNerf,
    poses: Sequence[tuple[str, np.ndarray]],
    intrinsics: Intrinsics | None = None,
    depths: Sequence[np.ndarray | None] | None = None,
    semantics: bool = True,
    sampler: str | None = None,
    appearance: int | None = None,
    color: bool = True,
    rays_per_pass: int | None = None,
    unseen_unknown: bool | None = None,
) -> list[RenderedView]:
    """Render the ``(name, pose)`` cameras, the rays of several views per forward pass (about
    ``rays_per_pass``; default 2^16 on a CPU, 2^18 on CUDA). ``depths``: each view's measured depth
    (or ``None``); views with depth and views without are batched separately, as they use different
    samplers. ``unseen_unknown``: see the module's description."""
    intr = intrinsics or nerf.info.intrinsics
    if unseen_unknown is None:
        unseen_unknown = nerf.config.render_unseen_unknown
    hw = intr.width * intr.height
    if rays_per_pass is None:
        rays_per_pass = 2**18 if nerf.device.type == "cuda" else 2**16
    depths = list(depths) if depths is not None else [None] * len(poses)
    if len(depths) != len(poses):
        raise ValueError(f"render_frames: {len(poses)} poses but {len(depths)} depth maps")
    has = [d is not None and bool((np.asarray(d) > 0).any()) for d in depths]
    per_pass = max(1, rays_per_pass // hw)
    views: dict[int, RenderedView] = {}
    for with_depth in (True, False):
        idx = [i for i in range(len(poses)) if has[i] == with_depth]
        for start in range(0, len(idx), per_pass):
            group = idx[start : start + per_pass]
            rays = [image_rays(intr, poses[i][1], nerf.device) for i in group]
            origins = torch.cat([o for o, _ in rays])
            dirs = torch.cat([d for _, d in rays])
            depth = None
            if with_depth:
                depth = torch.as_tensor(
                    np.concatenate([np.asarray(depths[i], np.float32).reshape(-1) for i in group]),
                    device=nerf.device,
                )
            out = nerf.render_rays(
                origins,
                dirs,
                sampler=sampler,
                depth=depth,
                semantics=semantics,
                appearance=appearance,
                color=color,
                # Band-only samples are few per ray: bigger chunks (colour marches whole rays,
                # and so do the labels of a config that does not render in the depth band).
                chunk=max(rays_per_pass, render_chunk(nerf.config.render_chunk, nerf.device))
                if with_depth and not color and nerf.config.sampler.render_depth_guided
                else None,
            )
            known = None
            if unseen_unknown and "semantics" in out:
                known = seen_surface(nerf, origins, dirs, out, depth)
            for k, i in enumerate(group):
                part = {key: v[k * hw : (k + 1) * hw] for key, v in out.items()}
                views[i] = _view_from_output(
                    part,
                    intr,
                    poses[i][1],
                    poses[i][0],
                    None if known is None else known[k * hw : (k + 1) * hw],
                )
    return [views[i] for i in range(len(poses))]


def render_views(
    nerf: SemanticNerf,
    scene: Scene | None = None,
    views: str = "train",
    semantics: bool = True,
    sampler: str | None = None,
    progress: bool = False,
    color: bool = True,
    unseen_unknown: bool | None = None,
) -> list[RenderedView]:
    """Render the ``views`` (train, val, all or novel) of a scene at the checkpoint's camera.
    With the scene, its frames' measured depth guides the samples where the config says so.
    ``unseen_unknown``: see the module's description."""
    poses = view_poses(nerf, views, scene)
    intr = scene.intrinsics if scene is not None else nerf.info.intrinsics
    depth_of = {}
    if scene is not None and views != "novel":
        depth_of = {f.name: f.depth for f in scene.frames}
    depths = [depth_of.get(name) for name, _ in poses]
    step = 8 if progress else len(poses) or 1  # views per progress update
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(poses), desc=f"render {views}", unit="view", dynamic_ncols=True)
    out: list[RenderedView] = []
    for i in range(0, len(poses), step):
        out += render_frames(
            nerf,
            poses[i : i + step],
            intr,
            depths[i : i + step],
            semantics=semantics,
            sampler=sampler,
            color=color,
            unseen_unknown=unseen_unknown,
        )
        if bar is not None:
            bar.update(len(poses[i : i + step]))
    if bar is not None:
        bar.close()
    return out


def render_pseudo_labels(
    nerf: SemanticNerf,
    scene: Scene | None = None,
    views: str = "train",
    sampler: str | None = None,
    unseen_unknown: bool | None = None,
) -> dict[str, np.ndarray]:
    """NYU40 pseudo-labels ``{frame name: (H, W) uint8}`` rendered at the ``views`` (labels
    only: no colour is computed); with ``unseen_unknown`` 0 where no training camera saw the
    surface (the segmentation loss skips those pixels)."""
    rendered = render_views(
        nerf,
        scene,
        views,
        semantics=True,
        sampler=sampler,
        color=False,
        unseen_unknown=unseen_unknown,
    )
    return {v.name: v.labels for v in rendered}


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
