"""``/api/v1/metrics/continual``: the R matrix and continual-learning scores of a lineage
(``server/services/continual.py``)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from server.auth import OperatorScope
from server.deps import DbDep
from server.schemas.common import ERROR_RESPONSES, Name
from server.schemas.continual import ContinualMetricsOut
from server.services import continual as metrics

router = APIRouter(
    prefix="/metrics", tags=["metrics"], responses=ERROR_RESPONSES, dependencies=[OperatorScope]
)


@router.get(
    "/continual",
    response_model=ContinualMetricsOut,
    summary="R matrix, ACC, A, FWT and BWT over the adaptation history",
)
def continual(
    db: DbDep,
    lineage: Annotated[
        Name | None, Query(description="default: the current model's lineage")
    ] = None,
    split: Annotated[Literal["val", "train", "all"], Query()] = "val",
) -> ContinualMetricsOut:
    """Step i is the i-th adaptation of the lineage (a version with an adapted scene), scene j
    the scene adapted to at step j. Entries come from evaluate and adapt jobs (latest wins)."""
    return metrics.continual_metrics(db, lineage, split)
