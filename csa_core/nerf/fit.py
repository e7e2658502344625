"""``fit_semantic_nerf``: fit a Semantic-NeRF to the posed RGB-D frames and labels of a scene.

Each step draws random rays from all training pixels, samples them (depth-guided in the
fast preset, the paper's uniform + importance sampler in the reference preset), renders
colour, depth and class distributions, and takes one Adam step on
L2 colour + 0.1 L1 depth + 0.04 NLL semantics (DESIGN.md "The method" step 2).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from csa_core.data.camera import Intrinsics
from csa_core.data.scene import Frame, Scene
from csa_core.device import resolve_device
from csa_core.errors import CSAInputError
from csa_core.nerf.config import NerfConfig, preset
from csa_core.nerf.losses import free_space_loss, psnr, total_loss
from csa_core.nerf.model import SceneInfo, SemanticNerf
from csa_core.nerf.normalization import scene_box_from_frames
from csa_core.nerf.rendering import RaySamples
from csa_core.progress import ProgressCallback

log = logging.getLogger(__name__)


@dataclass
class FitStats:
    """What a fit measured: wall time, steps, rays and samples per second, last losses."""

    seconds: float
    steps: int
    rays_per_second: float
    samples_per_second: float
    final_loss: float
    final_psnr: float
    occupied_fraction: float


def camera_directions(intr: Intrinsics, device: torch.device | str = "cpu") -> Tensor:
    """Unit-z camera-frame directions of every pixel centre, (H * W, 3), row-major."""
    v, u = torch.meshgrid(
        torch.arange(intr.height, dtype=torch.float64),
        torch.arange(intr.width, dtype=torch.float64),
        indexing="ij",
    )
    d = torch.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, torch.ones_like(u)], dim=-1)
    return d.reshape(-1, 3).to(device=device, dtype=torch.float32)


def image_rays(
    intr: Intrinsics, pose: np.ndarray, device: torch.device | str = "cpu"
) -> tuple[Tensor, Tensor]:
    """World origins and unit-z directions (H * W, 3) of every pixel of a camera at ``pose``."""
    p = torch.as_tensor(np.asarray(pose, dtype=np.float64), dtype=torch.float32, device=device)
    d = camera_directions(intr, device) @ p[:3, :3].T
    return p[:3, 3].expand_as(d).contiguous(), d


class _RayData:
    """All training pixels of a scene as flat tensors, with their camera index."""

    def __init__(
        self,
        frames: Sequence[Frame],
        intr: Intrinsics,
        label_folder: str | None,
        device: torch.device,
    ):
        hw = intr.width * intr.height
        self.hw = hw
        self.dirs_cam = camera_directions(intr, device)
        poses = torch.as_tensor(
            np.stack([np.asarray(f.pose, dtype=np.float64) for f in frames]),
            dtype=torch.float32,
            device=device,
        )
        self.rot = poses[:, :3, :3]
        self.origin = poses[:, :3, 3]
        self.rgb = torch.as_tensor(
            np.stack([f.color for f in frames]).reshape(-1, 3), device=device
        )
        depth = [
            f.depth if f.depth is not None else np.zeros(f.color.shape[:2], np.float32)
            for f in frames
        ]
        self.depth = torch.as_tensor(np.stack(depth).reshape(-1).astype(np.float32), device=device)
        self.labels = None
        if label_folder is not None:
            self.labels = torch.as_tensor(
                np.stack([f.labels[label_folder] for f in frames]).reshape(-1), device=device
            )
        self.count = self.rgb.shape[0]

    def batch(self, ids: Tensor) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        cam, pix = ids // self.hw, ids % self.hw
        dirs = torch.einsum("nij,nj->ni", self.rot[cam], self.dirs_cam[pix])
        target = {"rgb": self.rgb[ids].float() / 255.0, "depth": self.depth[ids], "frame": cam}
        if self.labels is not None:
            target["labels"] = self.labels[ids]
        return self.origin[cam], dirs, target


def check_fit_inputs(scene: Scene, label_folder: str | None, frames: Sequence[Frame]) -> None:
    """Refuse scenes that cannot be fitted, naming what is wrong."""
    where = scene.root or scene.name
    if len(scene.frames) < 2:
        raise CSAInputError(
            where, f"a NeRF needs at least 2 posed frames, the scene has {len(scene.frames)}"
        )
    if not frames:
        raise CSAInputError(where, "no training frames to fit")
    size = (scene.intrinsics.height, scene.intrinsics.width)
    for f in frames:
        if f.color.shape[:2] != size:
            raise CSAInputError(
                where,
                f"frame {f.name}: colour is {f.color.shape[1]}x{f.color.shape[0]}, scene is {size[1]}x{size[0]}",
            )
        if not np.all(np.isfinite(f.pose)):
            raise CSAInputError(where, f"frame {f.name}: pose is not finite")
        if label_folder is not None and label_folder not in f.labels:
            have = ", ".join(scene.label_folders) or "none"
            raise CSAInputError(
                where,
                f"frame {f.name} has no labels in '{label_folder}' (label folders read: {have})",
            )


def _in_front(samples: RaySamples, depth: Tensor, cfg: NerfConfig) -> Tensor:
    """Samples that end before the depth band of their ray (float mask; 0 on rays without depth)."""
    d = depth[samples.ray_indices]
    half = cfg.sampler.depth_band + cfg.sampler.depth_band_fraction * d
    return ((d > 0) & (samples.t_ends < d - half)).float()


def _make_optimizer(nerf: SemanticNerf, cfg: NerfConfig) -> torch.optim.Optimizer:
    o = cfg.optim
    tables = [
        p
        for n, p in nerf.field.named_parameters()
        if n.startswith("encoding.") or n == "semantic_table"
    ]
    mlp = [
        p
        for n, p in nerf.field.named_parameters()
        if not (n.startswith("encoding.") or n == "semantic_table")
    ]
    if nerf.appearance is not None:  # per-frame colour corrections: no decay, like the tables
        tables += list(nerf.appearance.parameters())
    groups = [
        {"params": tables, "weight_decay": 0.0},
        {"params": mlp, "weight_decay": o.weight_decay_mlp},
    ]
    kwargs = {"lr": o.lr, "betas": o.betas, "eps": o.eps}
    try:
        return torch.optim.Adam(groups, fused=True, **kwargs)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(groups, **kwargs)


def fit_semantic_nerf(
    scene: Scene,
    label_folder: str | None = "label-nyu40",
    config: NerfConfig | str = "fast",
    device: str | torch.device | None = None,
    frames: Sequence[Frame] | None = None,
    steps: int | None = None,
    progress: bool = True,
    on_progress: ProgressCallback | None = None,
) -> tuple[SemanticNerf, FitStats]:
    """Fit a Semantic-NeRF to ``frames`` (default: the scene's training frames) and the labels of
    ``label_folder`` (``None``: colour and depth only).

    ``config`` is a :class:`NerfConfig` or a preset name; ``steps`` overrides its step count.
    ``device``: ``None``/``"auto"`` picks CUDA when available. Returns the model (on ``device``,
    occupancy grid estimated) and the fit's statistics. ``on_progress(message, fraction)``
    (:mod:`csa_core.progress`) hears the step, loss and PSNR every 10 steps and after the last;
    what it raises propagates unchanged and ends the fit.
    """
    cfg = preset(config) if isinstance(config, str) else config
    dev = resolve_device(device)
    frames = list(scene.train_frames if frames is None else frames)
    check_fit_inputs(scene, label_folder, frames)
    n_steps = cfg.optim.steps if steps is None else int(steps)
    has_depth = any(f.depth is not None and bool((f.depth > 0).any()) for f in frames)
    train_sampler = cfg.sampler.train
    if train_sampler == "depth" and not has_depth:
        log.warning(
            "scene %s has no depth: depth-guided sampling falls back to the reference sampler",
            scene.name,
        )
        train_sampler = "reference"

    gen = torch.Generator().manual_seed(cfg.seed)
    box = scene_box_from_frames(frames, scene.intrinsics, seed=cfg.seed)
    info = SceneInfo(
        name=scene.name,
        intrinsics=scene.intrinsics,
        train_frames=[f.name for f in frames],
        train_poses=np.stack([np.asarray(f.pose, dtype=np.float64) for f in frames]),
        label_folder=label_folder,
    )
    with torch.random.fork_rng(
        devices=[]
    ):  # MLP initialisation from the config's seed, caller's RNG untouched
        torch.manual_seed(cfg.seed)
        nerf = SemanticNerf(cfg, box, info, generator=gen).to(dev)
    data = _RayData(frames, scene.intrinsics, label_folder, dev)
    opt = _make_optimizer(nerf, cfg)
    decay = math.exp(math.log(cfg.optim.final_lr_fraction) / max(1, n_steps))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, decay)
    dgen = torch.Generator(device=dev).manual_seed(cfg.seed)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(
            total=n_steps, desc=f"fit {scene.name} ({cfg.preset})", unit="step", dynamic_ncols=True
        )
    t0 = time.perf_counter()
    n_samples = 0
    metrics: dict[str, float] = {"loss": float("nan"), "psnr": float("nan")}
    nerf.train()
    for step in range(n_steps):
        ids = torch.randint(0, data.count, (cfg.optim.rays_per_step,), device=dev, generator=dgen)
        origins, dirs, target = data.batch(ids)
        if train_sampler == "occupancy" and step % cfg.sampler.occupancy_update_every == 0:
            nerf.grid.update(
                box, nerf.density_fn, decay=0.95, generator=dgen, fraction=0.25 if step else 1.0
            )
        samples = nerf.sample(
            origins, dirs, train_sampler, depth=target["depth"], stratified=True, generator=dgen
        )
        out = nerf.render_samples(
            origins, dirs, samples, semantics="labels" in target, appearance=target["frame"]
        )
        if cfg.loss.free_space > 0 and train_sampler == "depth":
            # Ramped in after a warm-up: carving before surfaces exist can kill the density (exp saturates at 0).
            warm = cfg.loss.free_space_warmup * n_steps
            ramp = min(1.0, max(0.0, (step - warm) / max(warm, 1.0)))
            if ramp > 0:
                out["free_space"] = ramp * free_space_loss(
                    out["weights"], _in_front(samples, target["depth"], cfg), samples
                )
        terms = total_loss(out, target, cfg.loss)
        opt.zero_grad(set_to_none=True)
        terms["loss"].backward()
        opt.step()
        sched.step()
        n_samples += len(samples)
        if step % 10 == 0 or step == n_steps - 1:
            metrics = {k: float(v.detach()) for k, v in terms.items()}
            metrics["psnr"] = psnr(metrics["color"])
            if bar is not None:
                bar.set_postfix(loss=f"{metrics['loss']:.4f}", psnr=f"{metrics['psnr']:.2f}")
            if on_progress is not None:
                on_progress(
                    f"NeRF step {step + 1}/{n_steps}  loss {metrics['loss']:.4f}"
                    f"  PSNR {metrics['psnr']:.2f}",
                    (step + 1) / n_steps,
                )
        if bar is not None:
            bar.update(1)
    nerf.eval()
    occupied = (
        nerf.update_occupancy(generator=dgen)
        if cfg.sampler.render == "occupancy" or train_sampler == "occupancy"
        else 1.0
    )
    seconds = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    stats = FitStats(
        seconds=seconds,
        steps=n_steps,
        rays_per_second=n_steps * cfg.optim.rays_per_step / max(seconds, 1e-9),
        samples_per_second=n_samples / max(seconds, 1e-9),
        final_loss=metrics["loss"],
        final_psnr=metrics["psnr"],
        occupied_fraction=occupied,
    )
    return nerf, stats
