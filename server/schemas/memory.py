from __future__ import annotations

from pydantic import BaseModel

from server.schemas.common import JsonObject, Timestamp


class NerfOut(BaseModel):
    """A scene's Semantic-NeRF in the memory bank."""

    id: int
    scene_id: int
    scene: str
    job_id: int | None
    size_bytes: int
    preset: str
    labels_source: str
    quality: JsonObject
    active: bool
    created_at: Timestamp


class MemoryBankOut(BaseModel):
    entries: list[NerfOut]
    total_bytes: int
    num_scenes: int
