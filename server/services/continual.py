"""Continual-learning metrics of a model lineage: the R matrix of its adaptation steps and
ACC, A, FWT and BWT (``/api/v1/metrics/continual``, the dashboard's continual page)."""

from __future__ import annotations

import math

from sqlalchemy import select
from sqlalchemy.orm import Session

from csa_core.eval import continual_metrics as score_continual
from server.db.models import Evaluation, Scene
from server.errors import not_found
from server.lookups import current_model
from server.registry import lineage_chain
from server.schemas.continual import ContinualMetricsOut, StepOut


def continual_metrics(db: Session, lineage: str | None, split: str = "val") -> ContinualMetricsOut:
    """Step i is the i-th adaptation of the lineage (default: the current model's; a version
    with an adapted scene), scene j the scene adapted to at step j. Entries come from evaluate
    and adapt jobs (latest wins). 404 without a current model or for an unknown lineage."""
    if lineage is None:
        cur = current_model(db)
        if cur is None:
            raise not_found("current model", "current")
        lineage = cur.lineage
    chain = lineage_chain(db, lineage)
    if not chain:
        raise not_found("lineage", lineage)
    root = chain[0]
    steps = [m for m in chain[1:] if m.adapted_scene_id is not None]
    scene_ids = [m.adapted_scene_id for m in steps]
    names: dict[int, str] = {}
    if scene_ids:
        named = db.execute(select(Scene.id, Scene.name).where(Scene.id.in_(scene_ids)))
        names = {i: n for i, n in named}
    latest: dict[tuple[int, int], float | None] = {}
    model_ids = [root.id] + [m.id for m in steps]
    entries = (
        select(Evaluation)
        .where(Evaluation.model_version_id.in_(model_ids), Evaluation.split == split)
        .order_by(Evaluation.id)
    )
    for ev in db.scalars(entries):
        latest[(ev.model_version_id, ev.scene_id)] = ev.miou
    R = [[latest.get((m.id, sid)) for sid in scene_ids] for m in steps]
    b = [latest.get((root.id, sid)) for sid in scene_ids]
    missing = [
        f"R[{i}][{j}]"
        for i in range(len(steps))
        for j in range(min(i + 2, len(steps)))
        if R[i][j] is None
    ]
    missing += [f"b[{j}]" for j in range(len(steps)) if b[j] is None]
    scores: dict[str, float | None] = {"acc": None, "a": None, "fwt": None, "bwt": None}
    if steps and not missing:
        nan = float("nan")
        raw = score_continual(
            [[nan if v is None else v for v in row] for row in R],
            [nan if v is None else v for v in b],
        )
        scores = {k: (v if math.isfinite(v) else None) for k, v in raw.items()}
    return ContinualMetricsOut(
        lineage=lineage,
        root_model_id=root.id,
        split=split,
        steps=[
            StepOut(
                step=i,
                model_id=m.id,
                model=m.name,
                scene_id=m.adapted_scene_id,
                scene=names.get(m.adapted_scene_id),
            )
            for i, m in enumerate(steps)
        ],
        R=R,
        b=b,
        missing=missing,
        **scores,
    )
