"""``pretrain``: train a new segmentation network on labelled scenes; a new lineage root.

``gather`` names the training and validation scenes, ``compute`` trains and saves the network,
``register`` adds it as the root version of the job's lineage."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from server.db.models import Job
from server.errors import conflict, invalid
from server.jobs.context import JobContext
from server.jobs.inputs import SceneInput, check_size, gather_scene, load_scene, torch_device
from server.jobs.phases import ApiNode
from server.lookups import get_scenes, require_ground_truth
from server.registry import register_checkpoint, root_conflict
from server.schemas.jobs import PretrainParams


def prepare(
    session: Session, params: PretrainParams, job: Job
) -> tuple[dict[str, Any], str | None]:
    from csa_core.seg import ARCH_NAMES, DEFAULT_ARCH

    arch = params.arch or DEFAULT_ARCH
    if arch not in ARCH_NAMES:
        raise invalid(
            "params.arch", f"unknown architecture {arch!r} (known: {', '.join(ARCH_NAMES)})"
        )
    scenes = get_scenes(session, params.scenes, "params.scenes")
    val = get_scenes(session, params.val_scenes or [], "params.val_scenes")
    both = sorted({s.name for s in scenes} & {s.name for s in val})
    if both:
        raise invalid("params.val_scenes", f"scene {both[0]!r} is also a training scene")
    for field, group in (("params.scenes", scenes), ("params.val_scenes", val)):
        for sc in group:
            require_ground_truth(session, sc, field)  # trains and scores on the uploaded labels
    size = check_size(params.size, scenes) or (
        scenes[0].intrinsics["width"],
        scenes[0].intrinsics["height"],
    )
    if min(size) < 8:
        raise invalid("params.size", "width and height must be at least 8")
    name = params.name or f"pretrain-{job.id}"
    lineage = params.lineage or name
    taken = root_conflict(session, name, lineage, "a pre-training")
    if taken is not None:
        raise conflict(taken[1], field=f"params.{taken[0]}")
    normalized = {
        "scene_ids": [s.id for s in scenes],
        "val_scene_ids": [s.id for s in val],
        "arch": arch,
        "epochs": params.epochs,
        "batch_size": params.batch_size,
        "lr": params.lr,
        "seed": params.seed,
        "size": list(size),
        "name": name,
        "make_current": params.make_current,
    }
    return normalized, lineage


@dataclass
class PretrainInputs:
    params: dict[str, Any]  # prepare's parameters
    scenes: list[SceneInput]
    val_scenes: list[SceneInput]


@dataclass
class PretrainOutputs:
    checkpoint: Path
    name: str
    arch: str
    metrics: dict[str, Any]
    meta: dict[str, Any]
    make_current: bool | None


def gather(session: Session, params: dict[str, Any], node: ApiNode) -> PretrainInputs:
    scenes = [gather_scene(session, node.store, sid) for sid in params["scene_ids"]]
    val = [gather_scene(session, node.store, sid) for sid in params["val_scene_ids"]]
    return PretrainInputs(dict(params), scenes, val)


def compute(inputs: PretrainInputs, workdir: Path, ctx: JobContext) -> PretrainOutputs:
    from csa_core.seg import PretrainConfig, TrainConfig, pretrain

    p = inputs.params
    size = (int(p["size"][0]), int(p["size"][1]))
    scenes, val = [], []
    stored = inputs.scenes + inputs.val_scenes
    for i, scene in enumerate(stored):
        ctx.progress(0.1 * i / len(stored), f"reading scene {scene.id}")
        read = load_scene(scene, workdir, ground_truth=True, size=size)
        (scenes if i < len(inputs.scenes) else val).append(read)
    config = PretrainConfig(
        arch=p["arch"],
        size=size,
        train=TrainConfig(
            epochs=p["epochs"],
            batch_size=p["batch_size"],
            lr=p["lr"],
            seed=p["seed"],
            device=torch_device(ctx),
            progress=False,
        ),
    )
    ctx.progress(0.1, f"training {p['arch']} for {p['epochs']} epoch(s)", force=True)
    out = workdir / "model.safetensors"
    _, result = pretrain(
        scenes, config, out=out, val_scenes=val or None, on_progress=ctx.core_progress(0.1, 0.95)
    )
    ctx.progress(0.95, "registering the model", force=True)
    score = result.best_score
    metrics = {
        "val_miou": score if score is not None and math.isfinite(score) else None,
        "val_miou_per_scene": {
            k: (v if math.isfinite(v) else None) for k, v in result.best_val_miou.items()
        },
        "best_epoch": result.best_epoch,
        "train_seconds": round(result.seconds, 2),
    }
    meta = {"task": "pretrain", "scene_ids": p["scene_ids"], "size": p["size"]}
    return PretrainOutputs(out, p["name"], p["arch"], metrics, meta, p["make_current"])


def register(s: Session, outputs: PretrainOutputs, node: ApiNode) -> dict[str, Any]:
    job = s.get(Job, node.job_id)
    model = register_checkpoint(
        s,
        node.store,
        outputs.checkpoint,
        name=outputs.name,
        lineage=job.lineage if job and job.lineage else outputs.name,
        arch=outputs.arch,
        job_id=node.job_id,
        metrics=outputs.metrics,
        meta=outputs.meta,
        make_current=outputs.make_current,
    )
    return {
        "model_id": model.id,
        "model": model.name,
        "lineage": model.lineage,
        "metrics": outputs.metrics,
    }
