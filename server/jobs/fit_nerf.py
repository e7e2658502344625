"""``fit_nerf``: fit a Semantic-NeRF to a stored scene and add it to the memory bank.

The labels fused into the NeRF are the current model's predictions (the method), the
uploaded ground truth (an oracle, for checks) or none. The fit, checkpoint and quality
numbers come from ``csa_core.nerf``. ``gather`` names the scene's frames (and the model's
checkpoint for predictions), ``compute`` fits and saves the NeRF, ``register`` makes it the
scene's active memory-bank entry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from server import capabilities
from server.db.models import Job
from server.errors import invalid, not_available
from server.jobs.context import JobContext
from server.jobs.inputs import (
    ModelInput,
    SceneInput,
    check_size,
    gather_model,
    gather_scene,
    load_scene,
    model_file,
    parse_size,
    torch_device,
)
from server.jobs.phases import ApiNode
from server.lookups import get_model, get_scene
from server.memory_bank import NERF_FILE, add_nerf
from server.schemas.jobs import FitNerfParams

PREDICTIONS_FOLDER = "predictions"


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def held_out_quality(nerf: Any, scene: Any) -> dict[str, float | None]:
    """Colour PSNR and depth error of the NeRF on the scene's validation views (never trained
    on)."""
    from csa_core.nerf.losses import psnr
    from csa_core.nerf.render import render_views

    frames = scene.val_frames
    if not frames:
        return {}
    views = render_views(nerf, scene, "val", semantics=False)
    mse = float(
        np.mean(
            [
                np.mean((v.color.astype(np.float64) - f.color.astype(np.float64)) ** 2) / 255.0**2
                for v, f in zip(views, frames, strict=True)
            ]
        )
    )
    errors = [
        np.abs(v.depth - f.depth)[f.depth > 0]
        for v, f in zip(views, frames, strict=True)
        if f.depth is not None
    ]
    errors = [e for e in errors if e.size]
    return {
        "val_psnr": _finite(psnr(mse)),
        "val_depth_mae_m": _finite(float(np.mean(np.concatenate(errors)))) if errors else None,
        "val_views": len(frames),
    }


def prepare(session: Session, params: FitNerfParams, job: Job) -> tuple[dict[str, Any], str | None]:
    scene = get_scene(session, params.scene)
    if scene.intrinsics is None:
        raise invalid("params.scene", f"scene {scene.name!r} has no frames")
    normalized: dict[str, Any] = params.model_dump(exclude={"scene", "model"}) | {
        "scene_id": scene.id
    }
    if params.labels == "predictions":
        reason = capabilities.missing_reason("seg")
        if reason is not None:
            raise not_available(f"labels=predictions needs a segmentation model: {reason}")
        normalized["model_id"] = get_model(session, params.model).id
    if params.size is not None:
        w, h = check_size(params.size, [scene])
        if min(w, h) < 8:
            raise invalid("params.size", "width and height must be at least 8")
    return normalized, None


@dataclass
class FitNerfInputs:
    params: dict[str, Any]  # prepare's parameters
    scene: SceneInput
    model: ModelInput | None  # the version that predicts the labels (labels=predictions)


@dataclass
class FitNerfOutputs:
    scene_id: int
    nerf: Path
    preset: str
    labels_source: str
    quality: dict[str, Any]


def gather(session: Session, params: dict[str, Any], node: ApiNode) -> FitNerfInputs:
    scene = gather_scene(session, node.store, params["scene_id"])
    model = (
        gather_model(session, node.store, params["model_id"])
        if params["labels"] == "predictions"
        else None
    )
    return FitNerfInputs(dict(params), scene, model)


def compute(inputs: FitNerfInputs, workdir: Path, ctx: JobContext) -> FitNerfOutputs:
    from csa_core.nerf.checkpoint import save_checkpoint
    from csa_core.nerf.config import build_config, preset
    from csa_core.nerf.fit import fit_semantic_nerf

    p = inputs.params
    size = parse_size(p.get("size"))
    ctx.progress(0.0, "reading the scene")
    scene = load_scene(inputs.scene, workdir, ground_truth=p["labels"] == "ground_truth", size=size)
    label_folder: str | None = None
    source = p["labels"]
    if p["labels"] == "ground_truth":
        label_folder = "label-nyu40"
    elif p["labels"] == "predictions":
        from csa_core.seg import load_checkpoint, predict_scene

        assert inputs.model is not None
        net, card = load_checkpoint(
            model_file(inputs.model, workdir), device=torch_device(ctx) or "cpu"
        )
        ctx.progress(0.02, f"predicting labels with {inputs.model.name}")
        preds = predict_scene(
            net,
            scene,
            split="train",
            device=torch_device(ctx),
            size=tuple(card.input_size) if card.input_size else None,
        )
        for frame in scene.train_frames:
            frame.labels[PREDICTIONS_FOLDER] = preds[frame.name]
        label_folder, source = PREDICTIONS_FOLDER, f"predictions:{inputs.model.name}"
        del net

    items = []
    if p.get("rays_per_step"):
        # A smaller fit (previews, tests) takes smaller semantic steps after it as well.
        rays = p["rays_per_step"]
        semantic = min(preset(p["preset"]).optim.semantic_rays_per_step, rays)
        items += [f"optim.rays_per_step={rays}", f"optim.semantic_rays_per_step={semantic}"]
    if p.get("occupancy_resolution"):
        items.append(f"sampler.occupancy_resolution={p['occupancy_resolution']}")
    if p.get("log2_table_size"):
        items.append(f"field.encoding.log2_table_size={p['log2_table_size']}")
    config = build_config(p["preset"], items, flag="fit_nerf parameters")
    total = p["steps"] or config.optim.steps

    ctx.progress(0.05, f"fitting ({p['preset']}, {total} steps)", force=True)
    nerf, stats = fit_semantic_nerf(
        scene,
        label_folder=label_folder,
        config=config,
        device=torch_device(ctx),
        steps=p["steps"],
        progress=False,
        on_progress=ctx.core_progress(0.05, 0.95),
    )
    ctx.check()
    out = workdir / NERF_FILE
    save_checkpoint(nerf, out)
    ctx.progress(0.96, "rendering the validation views", force=True)
    quality = {
        "preset": p["preset"],
        "train_psnr": _finite(stats.final_psnr),
        "final_loss": _finite(stats.final_loss),
        "fit_seconds": round(stats.seconds, 2),
        "steps": stats.steps,
    }
    quality |= held_out_quality(nerf, scene)
    return FitNerfOutputs(inputs.scene.id, out, p["preset"], source, quality)


def register(s: Session, outputs: FitNerfOutputs, node: ApiNode) -> dict[str, Any]:
    entry = add_nerf(
        s,
        node.store,
        outputs.scene_id,
        outputs.nerf,
        job_id=node.job_id,
        preset=outputs.preset,
        labels_source=outputs.labels_source,
        quality=outputs.quality,
    )
    return {
        "nerf_id": entry.id,
        "scene_id": outputs.scene_id,
        "size_bytes": entry.size_bytes,
        "quality": outputs.quality,
    }
