"""Typed results of the client (the server's JSON bodies, validated on arrival)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict


class _Result(BaseModel):
    model_config = ConfigDict(extra="allow")


class Health(_Result):
    status: str
    version: str
    database: str
    workers_alive: int
    capabilities: dict[str, str | None]


class Intrinsics(_Result):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


class Scene(_Result):
    id: int
    name: str
    description: str = ""
    intrinsics: Intrinsics | None = None
    num_frames: int
    num_labelled_frames: int
    has_nerf: bool
    created_at: dt.datetime


class Frame(_Result):
    id: int
    scene_id: int
    name: str
    pose: list[list[float]]
    has_labels: bool
    created_at: dt.datetime


class FrameUpload(Frame):
    created: bool
    replaced: bool = False


class SkippedFrame(_Result):
    name: str
    reason: str


class ArchiveUpload(_Result):
    scene_id: int
    added: list[str]
    unchanged: list[str]
    replaced: list[str]
    skipped: list[SkippedFrame]


class Job(_Result):
    id: int
    kind: str
    status: str
    params: dict[str, Any]
    lineage: str | None = None
    progress: float
    message: str
    result: dict[str, Any] | None = None
    error: str | None = None
    cancel_requested: bool = False
    attempts: int = 0
    worker_id: str | None = None
    created_at: dt.datetime
    started_at: dt.datetime | None = None
    finished_at: dt.datetime | None = None

    @property
    def done(self) -> bool:
        return self.status in ("succeeded", "failed", "cancelled")


class JobKind(_Result):
    kind: str
    description: str
    available: bool
    reason: str | None = None


class LogLine(_Result):
    time: dt.datetime
    level: str
    message: str


class ModelVersion(_Result):
    id: int
    name: str
    lineage: str
    parent_id: int | None = None
    children: list[int] = []
    adapted_scene_id: int | None = None
    adapted_scene: str | None = None
    job_id: int | None = None
    arch: str
    size_bytes: int
    sha256: str
    metrics: dict[str, Any] = {}
    evaluations: dict[str, float | None] = {}
    is_current: bool
    created_at: dt.datetime


class Nerf(_Result):
    id: int
    scene_id: int
    scene: str
    job_id: int | None = None
    size_bytes: int
    preset: str
    labels_source: str
    quality: dict[str, Any]
    active: bool
    created_at: dt.datetime


class MemoryBank(_Result):
    entries: list[Nerf]
    total_bytes: int
    num_scenes: int


class Step(_Result):
    step: int
    model_id: int
    model: str
    scene_id: int | None = None
    scene: str | None = None


class ContinualMetrics(_Result):
    lineage: str
    root_model_id: int | None
    split: str
    steps: list[Step]
    R: list[list[float | None]]
    b: list[float | None]
    acc: float | None = None
    a: float | None = None
    fwt: float | None = None
    bwt: float | None = None
    missing: list[str] = []


@dataclass(frozen=True)
class Prediction:
    """A label map as PNG bytes (uint8 NYU40 ids, or the palette picture) and the version used."""

    png: bytes
    model_id: int
    model: str


@dataclass(frozen=True)
class Rendering:
    """PNG bytes per channel: color (RGB), depth (uint16 mm), labels (uint8 NYU40 ids),
    labels_color."""

    scene_id: int
    nerf_id: int
    width: int
    height: int
    images: dict[str, bytes]
