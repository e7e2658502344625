from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from server.schemas.common import Camera, Pose, RowId

Channel = Literal["color", "depth", "labels", "labels_color"]


class RenderRequest(BaseModel):
    """A view of a scene's NeRF: camera-to-world pose (metres, OpenCV axes) and camera."""

    model_config = ConfigDict(extra="forbid")

    pose: Pose
    intrinsics: Camera | None = Field(default=None, description="default: the scene's camera")
    channels: list[Channel] = Field(
        default_factory=lambda: ["color", "depth", "labels"], min_length=1, max_length=4
    )
    nerf_id: RowId | None = Field(default=None, description="default: the scene's active NeRF")


class RenderOut(BaseModel):
    """PNG images, base64-encoded: colour (RGB), depth (uint16 mm), labels (uint8 NYU40 ids),
    labels_color (palette preview)."""

    scene_id: int
    nerf_id: int
    width: int
    height: int
    images: dict[str, str]
