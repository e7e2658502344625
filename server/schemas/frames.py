from __future__ import annotations

from pydantic import BaseModel, computed_field

from server.schemas.common import RecordOut, Timestamp


class FrameOut(RecordOut):
    id: int
    scene_id: int
    name: str
    pose: list[list[float]]
    color_sha256: str
    depth_sha256: str
    labels_sha256: str | None
    created_at: Timestamp

    @computed_field
    @property
    def has_labels(self) -> bool:
        return self.labels_sha256 is not None


class FrameUploadOut(FrameOut):
    created: bool  # false: the same content was already stored (idempotent re-upload)
    replaced: bool = False


class SkippedFrameOut(BaseModel):
    name: str
    reason: str


class ArchiveUploadOut(BaseModel):
    scene_id: int
    added: list[str]
    unchanged: list[str]
    replaced: list[str]
    skipped: list[SkippedFrameOut]
