"""``pretrain``: train a new segmentation network on labelled scenes; a new lineage root."""

from __future__ import annotations

import math
from typing import Any

from sqlalchemy.orm import Session

from server.db.models import Job
from server.errors import conflict, invalid
from server.jobs.context import JobContext
from server.jobs.inputs import check_size, load_scene, torch_device
from server.lookups import get_scenes, require_ground_truth
from server.registry import register_checkpoint, root_conflict
from server.schemas.jobs import PretrainParams


def prepare(session: Session, params: PretrainParams, job: Job) -> tuple[dict[str, Any], str | None]:
    from csa_core.seg import ARCH_NAMES, DEFAULT_ARCH

    arch = params.arch or DEFAULT_ARCH
    if arch not in ARCH_NAMES:
        raise invalid("params.arch", f"unknown architecture {arch!r} (known: {', '.join(ARCH_NAMES)})")
    scenes = get_scenes(session, params.scenes, "params.scenes")
    val = get_scenes(session, params.val_scenes or [], "params.val_scenes")
    both = sorted({s.name for s in scenes} & {s.name for s in val})
    if both:
        raise invalid("params.val_scenes", f"scene {both[0]!r} is also a training scene")
    for field, group in (("params.scenes", scenes), ("params.val_scenes", val)):
        for sc in group:
            require_ground_truth(session, sc, field)  # trains and scores on the uploaded labels
    size = check_size(params.size, scenes) or (scenes[0].intrinsics["width"], scenes[0].intrinsics["height"])
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


def run(ctx: JobContext) -> None:
    from csa_core.seg import PretrainConfig, TrainConfig, pretrain

    p = ctx.params
    size = (int(p["size"][0]), int(p["size"][1]))
    scenes, val = [], []
    ids = p["scene_ids"] + p["val_scene_ids"]
    for i, sid in enumerate(ids):
        ctx.progress(0.1 * i / len(ids), f"reading scene {sid}")
        (scenes if i < len(p["scene_ids"]) else val).append(load_scene(ctx, sid, ground_truth=True, size=size))
    config = PretrainConfig(
        arch=p["arch"],
        size=size,
        train=TrainConfig(epochs=p["epochs"], batch_size=p["batch_size"], lr=p["lr"], seed=p["seed"], device=torch_device(ctx), progress=False),
    )
    ctx.progress(0.1, f"training {p['arch']} for {p['epochs']} epoch(s)", force=True)
    out = ctx.workdir / "model.safetensors"
    _, result = pretrain(scenes, config, out=out, val_scenes=val or None, on_progress=ctx.core_progress(0.1, 0.95))
    ctx.progress(0.95, "registering the model", force=True)
    score = result.best_score
    metrics = {
        "val_miou": score if score is not None and math.isfinite(score) else None,
        "val_miou_per_scene": {k: (v if math.isfinite(v) else None) for k, v in result.best_val_miou.items()},
        "best_epoch": result.best_epoch,
        "train_seconds": round(result.seconds, 2),
    }

    def register(s: Session) -> dict[str, Any]:
        job = s.get(Job, ctx.job_id)
        model = register_checkpoint(
            s,
            ctx.store,
            out,
            name=p["name"],
            lineage=job.lineage if job and job.lineage else p["name"],
            arch=p["arch"],
            job_id=ctx.job_id,
            metrics=metrics,
            meta={"task": "pretrain", "scene_ids": p["scene_ids"], "size": p["size"]},
            make_current=p["make_current"],
        )
        return {"model_id": model.id, "model": model.name, "lineage": model.lineage, "metrics": metrics}

    ctx.complete(register)
