"""``fit_semantic_nerf``: fit a Semantic-NeRF to the posed RGB-D frames and labels of a scene.

A fresh model trained by :class:`~csa_core.nerf.trainer.NerfTrainer` (the loop joint
training uses too): each step draws random rays from all training pixels, samples them
(depth-guided in the fast preset, the paper's uniform + importance sampler in the reference
preset), renders colour, depth and class distributions, and takes one Adam step on
L2 colour + 0.1 L1 depth + 0.04 NLL semantics (docs/method.md "Fuse in 3D").
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from csa_core.data.camera import check_pose
from csa_core.data.nyu40 import check_label_map
from csa_core.data.scene import Frame, Scene, check_depth
from csa_core.device import resolve_device
from csa_core.errors import CSAInputError
from csa_core.nerf.config import NerfConfig, preset, scaled_semantic_steps
from csa_core.nerf.losses import psnr
from csa_core.nerf.model import SceneInfo, SemanticNerf
from csa_core.nerf.normalization import fitted_box
from csa_core.nerf.rays import RayBank
from csa_core.nerf.samplers import OccupancySampler
from csa_core.nerf.trainer import NerfTrainer
from csa_core.progress import ProgressCallback

log = logging.getLogger(__name__)


@dataclass
class FitStats:
    """What a fit measured: wall time (the semantic steps after the fit included), steps, rays
    and samples per second of the fit's own steps, last losses."""

    seconds: float
    steps: int
    rays_per_second: float
    samples_per_second: float
    final_loss: float
    final_psnr: float
    occupied_fraction: float


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
                f"frame {f.name}: colour is {f.color.shape[1]}x{f.color.shape[0]}, scene is "
                f"{size[1]}x{size[0]}",
            )
        try:
            check_pose(f.pose, where)
        except CSAInputError as e:
            raise CSAInputError(where, f"frame {f.name}: {e.problem}") from None
        if label_folder is not None and label_folder not in f.labels:
            have = ", ".join(scene.label_folders) or "none"
            raise CSAInputError(
                where,
                f"frame {f.name} has no labels in '{label_folder}' (label folders read: {have})",
            )
        if label_folder is not None:
            what = f"frame {f.name}: labels '{label_folder}'"
            try:
                labels = check_label_map(f.labels[label_folder], what)
            except ValueError as e:
                raise CSAInputError(where, str(e)) from None
            if labels.shape != size:
                got = f"{labels.shape[1]}x{labels.shape[0]}"
                raise CSAInputError(where, f"{what} are {got}, scene is {size[1]}x{size[0]}")
    check_depth(frames, where)


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

    ``config`` is a :class:`NerfConfig` or a preset name; ``steps`` overrides its step count,
    and the semantic-head steps after the fit (``optim.semantic_steps``) scale with it (a tenth
    of the fit's steps keeps a tenth of the semantic steps, rounded up).
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
    semantic_steps = scaled_semantic_steps(cfg.optim, steps)
    if (
        label_folder is not None
        and not cfg.optim.semantics_in_fit
        and cfg.optim.semantic_steps <= 0
    ):
        raise ValueError(
            "optim.semantics_in_fit=false leaves the semantic head untrained unless "
            "optim.semantic_steps > 0"
        )
    has_depth = any(f.depth is not None and bool((f.depth > 0).any()) for f in frames)
    if cfg.sampler.train == "depth" and not has_depth:
        log.warning(
            "scene %s has no depth: depth-guided sampling falls back to the reference sampler",
            scene.name,
        )

    gen = torch.Generator().manual_seed(cfg.seed)
    box = fitted_box(frames, scene.intrinsics, cfg)
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
        torch.default_generator.manual_seed(cfg.seed)  # the CPU's: the model is built there
        nerf = SemanticNerf(cfg, box, info, generator=gen).to(dev)
    rays = RayBank(frames, scene.intrinsics, dev, label_folder)
    trainer = NerfTrainer(
        nerf,
        rays,
        schedule_steps=n_steps,
        free_space_warmup=cfg.loss.free_space_warmup * n_steps,
        seed=cfg.seed,
        semantics=cfg.optim.semantics_in_fit,
    )

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(
            total=n_steps, desc=f"fit {scene.name} ({cfg.preset})", unit="step", dynamic_ncols=True
        )
    metrics: dict[str, float] = {"loss": float("nan"), "psnr": float("nan")}

    def report(step: int, terms: dict[str, torch.Tensor]) -> None:
        if step % 10 == 0 or step == n_steps - 1:
            metrics.update({k: float(v.detach()) for k, v in terms.items()})
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

    t0 = time.perf_counter()
    try:
        trainer.train(n_steps, on_step=report)
    finally:
        if bar is not None:
            bar.close()
    fit_seconds = time.perf_counter() - t0
    uses_grid = cfg.sampler.render == "occupancy" or isinstance(trainer.sampler, OccupancySampler)
    occupied = nerf.update_occupancy(generator=trainer.generator) if uses_grid else 1.0
    o = cfg.optim
    if label_folder is not None and semantic_steps > 0:

        def semantic_report(i: int) -> None:
            # Every 10 steps and after the last, like the fit's steps (a cancel lands there).
            if on_progress is not None and (i % 10 == 0 or i == semantic_steps - 1):
                on_progress(f"NeRF semantic step {i + 1}/{semantic_steps}", 1.0)

        trainer.semantic_steps(
            semantic_steps,
            lr=o.lr * o.semantic_lr_fraction,
            rays_per_step=o.semantic_rays_per_step,
            on_step=semantic_report,
        )
    seconds = time.perf_counter() - t0
    stats = FitStats(
        seconds=seconds,
        steps=n_steps,
        rays_per_second=n_steps * trainer.rays_per_step / max(fit_seconds, 1e-9),
        samples_per_second=trainer.samples_seen / max(fit_seconds, 1e-9),
        final_loss=metrics["loss"],
        final_psnr=metrics["psnr"],
        occupied_fraction=occupied,
    )
    return nerf, stats
