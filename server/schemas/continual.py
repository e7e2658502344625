from __future__ import annotations

from pydantic import BaseModel


class StepOut(BaseModel):
    """Step i of the continual chain: the version made by adapting to scene i."""

    step: int
    model_id: int
    model: str
    scene_id: int | None
    scene: str | None


class ContinualMetricsOut(BaseModel):
    """R[i][j]: mIoU on scene j's validation views after step i; b[j]: the root (pre-trained)
    version on scene j; ACC, A, FWT, BWT from them (null while entries are missing)."""

    lineage: str
    root_model_id: int | None
    split: str
    steps: list[StepOut]
    R: list[list[float | None]]
    b: list[float | None]
    acc: float | None
    a: float | None
    fwt: float | None
    bwt: float | None
    missing: list[str]
