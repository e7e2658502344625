from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from server.schemas.common import IntrinsicsOut, Name, PlainText, Timestamp


class SceneCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: Name
    description: PlainText = Field(default="", max_length=2000)


class SceneOut(BaseModel):
    id: int
    name: str
    description: str
    intrinsics: IntrinsicsOut | None
    depth_size: tuple[int, int] | None = None
    num_frames: int
    num_labelled_frames: int
    has_nerf: bool
    created_at: Timestamp
