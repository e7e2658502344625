"""``evaluate``: mIoU of a model version on scenes with ground truth (the R matrix entries).

``gather`` names the version's checkpoint and the scenes, ``compute`` scores it on each scene's
split, ``register`` adds one evaluation per scene."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.db.models import Evaluation, Frame, Job, Scene
from server.errors import invalid
from server.jobs.context import JobContext
from server.jobs.inputs import (
    ModelInput,
    SceneInput,
    gather_model,
    gather_scene,
    load_scene,
    model_file,
    torch_device,
)
from server.jobs.phases import ApiNode
from server.lookups import get_model, get_scenes, require_ground_truth
from server.schemas.jobs import EvaluateParams


def fully_labelled_scenes(session: Session) -> list[Scene]:
    counts = (
        select(
            Frame.scene_id,
            func.count(Frame.id).label("n"),
            func.count(Frame.labels_sha256).label("labelled"),
        )
        .group_by(Frame.scene_id)
        .subquery()
    )
    return list(
        session.scalars(
            select(Scene)
            .join(counts, counts.c.scene_id == Scene.id)
            .where(counts.c.n == counts.c.labelled)
            .order_by(Scene.id)
        )
    )


def prepare(
    session: Session, params: EvaluateParams, job: Job
) -> tuple[dict[str, Any], str | None]:
    model = get_model(session, params.model)
    if params.scenes is None:
        scenes = fully_labelled_scenes(session)
        if not scenes:
            raise invalid("params.scenes", "no scene has ground-truth labels on every frame")
    else:
        scenes = [
            require_ground_truth(session, sc, "params.scenes")
            for sc in get_scenes(session, params.scenes, "params.scenes")
        ]
    return {"model_id": model.id, "scene_ids": [s.id for s in scenes], "split": params.split}, None


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


@dataclass
class EvaluateInputs:
    model: ModelInput
    scenes: list[SceneInput]
    split: str


@dataclass
class SceneScore:
    scene_id: int
    summary: dict[str, Any]  # csa_core.eval.miou.ConfusionMatrix.summary()


@dataclass
class EvaluateOutputs:
    model_id: int
    split: str
    scores: list[SceneScore]


def gather(session: Session, params: dict[str, Any], node: ApiNode) -> EvaluateInputs:
    model = gather_model(session, node.store, params["model_id"])
    scenes = [gather_scene(session, node.store, sid) for sid in params["scene_ids"]]
    return EvaluateInputs(model, scenes, params["split"])


def compute(inputs: EvaluateInputs, workdir: Path, ctx: JobContext) -> EvaluateOutputs:
    from csa_core.seg import evaluate_scene, load_checkpoint

    device = torch_device(ctx)
    net, card = load_checkpoint(model_file(inputs.model, workdir), device=device or "cpu")
    size = tuple(card.input_size) if card.input_size else None
    scores = []
    for i, stored in enumerate(inputs.scenes):
        ctx.progress(i / len(inputs.scenes), f"scene {stored.id}: reading")
        scene = load_scene(stored, workdir, ground_truth=True, size=size)
        ctx.progress(None, f"scene {scene.name}: predicting {len(scene.split(inputs.split))} views")
        matrix = evaluate_scene(net, scene, split=inputs.split, device=device)
        summary = matrix.summary()
        scores.append(SceneScore(stored.id, summary))
        miou = f"mIoU {100 * summary['miou']:.1f}%"
        ctx.log(f"{inputs.model.name} on {scene.name} ({inputs.split}): {miou}")
    return EvaluateOutputs(inputs.model.id, inputs.split, scores)


def register(s: Session, outputs: EvaluateOutputs, node: ApiNode) -> dict[str, Any]:
    out = {}
    # A scene named twice counts once.
    summaries = {score.scene_id: score.summary for score in outputs.scores}
    for scene_id, summary in summaries.items():
        miou = _finite(summary["miou"])
        s.add(
            Evaluation(
                model_version_id=outputs.model_id,
                scene_id=scene_id,
                split=outputs.split,
                miou=miou,
                summary=summary,
                job_id=node.job_id,
            )
        )
        out[str(scene_id)] = miou
    return {"model_id": outputs.model_id, "split": outputs.split, "miou": out}
