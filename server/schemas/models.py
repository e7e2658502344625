from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from server.schemas.common import Timestamp


class ModelOut(BaseModel):
    """A model version with its place in the lineage and its scores."""

    id: int
    name: str
    lineage: str
    parent_id: int | None
    children: list[int]
    adapted_scene_id: int | None
    adapted_scene: str | None
    job_id: int | None
    arch: str
    size_bytes: int
    sha256: str
    metrics: dict[str, Any]
    evaluations: dict[str, float | None]  # "scene/split" -> mIoU
    is_current: bool
    created_at: Timestamp
