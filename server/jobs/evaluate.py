"""``evaluate``: mIoU of a model version on scenes with ground truth (the R matrix entries)."""

from __future__ import annotations

import math
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.db.models import Evaluation, Frame, Job, Scene
from server.errors import invalid
from server.jobs.context import JobContext
from server.jobs.inputs import load_scene, model_file, torch_device
from server.lookups import get_model, get_scenes, require_ground_truth
from server.schemas.jobs import EvaluateParams


def fully_labelled_scenes(session: Session) -> list[Scene]:
    counts = (
        select(Frame.scene_id, func.count(Frame.id).label("n"), func.count(Frame.labels_sha256).label("labelled"))
        .group_by(Frame.scene_id)
        .subquery()
    )
    return list(session.scalars(select(Scene).join(counts, counts.c.scene_id == Scene.id).where(counts.c.n == counts.c.labelled).order_by(Scene.id)))


def prepare(session: Session, params: EvaluateParams, job: Job) -> tuple[dict[str, Any], str | None]:
    model = get_model(session, params.model)
    if params.scenes is None:
        scenes = fully_labelled_scenes(session)
        if not scenes:
            raise invalid("params.scenes", "no scene has ground-truth labels on every frame")
    else:
        scenes = [require_ground_truth(session, sc, "params.scenes") for sc in get_scenes(session, params.scenes, "params.scenes")]
    return {"model_id": model.id, "scene_ids": [s.id for s in scenes], "split": params.split}, None


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def run(ctx: JobContext) -> None:
    from csa_core.seg import evaluate_scene, load_checkpoint

    p = ctx.params
    path, model_row = model_file(ctx, p["model_id"])
    net, card = load_checkpoint(path, device=torch_device(ctx) or "cpu")
    size = tuple(card.input_size) if card.input_size else None
    scores: dict[int, dict[str, Any]] = {}
    for i, scene_id in enumerate(p["scene_ids"]):
        ctx.progress(i / len(p["scene_ids"]), f"scene {scene_id}: reading")
        scene = load_scene(ctx, scene_id, ground_truth=True, size=size)
        ctx.progress(None, f"scene {scene.name}: predicting {len(scene.split(p['split']))} views")
        matrix = evaluate_scene(net, scene, split=p["split"], device=torch_device(ctx))
        summary = matrix.summary()
        scores[scene_id] = summary
        ctx.log(f"{model_row.name} on {scene.name} ({p['split']}): mIoU {100 * summary['miou']:.1f}%")

    def register(s: Session) -> dict[str, Any]:
        out = {}
        for scene_id, summary in scores.items():
            miou = _finite(summary["miou"])
            s.add(Evaluation(model_version_id=p["model_id"], scene_id=scene_id, split=p["split"], miou=miou, summary=summary, job_id=ctx.job_id))
            out[str(scene_id)] = miou
        return {"model_id": p["model_id"], "split": p["split"], "miou": out}

    ctx.complete(register)
