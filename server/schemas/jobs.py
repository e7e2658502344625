"""Jobs: one request body per kind (a discriminated union on ``kind``) and the job's state."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, ConfigDict, Field

from csa_core.data.camera import parse_size
from server.db.models import MAX_ID
from server.schemas.common import JsonObject, Name, RecordOut, Ref, Timestamp, core_rule

# An image size, checked by the core's parser of sizes (the CLI's rule).
Size = Annotated[
    str,
    Field(pattern=r"^[0-9]{1,4}x[0-9]{1,4}$", description="WxH, e.g. 160x120"),
    core_rule("size", lambda text: parse_size(text, "size")),
]


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FitNerfParams(_Params):
    """Fit a Semantic-NeRF to a scene and keep it in the memory bank."""

    scene: Ref
    labels: Literal["predictions", "ground_truth", "none"] = Field(
        default="predictions",
        description="labels to fuse: the model's predictions (the method), the uploaded ground "
        "truth (oracle), or none",
    )
    model: Ref | None = Field(
        default=None, description="model version that predicts the labels (default: current)"
    )
    preset: Literal["fast", "reference"] = "fast"
    steps: int | None = Field(
        default=None, ge=1, le=200_000, description="override the preset's step count"
    )
    size: Size | None = Field(
        default=None, description="working size (default: the scene's colour size)"
    )
    # Smaller fits for previews and tests; the presets' values otherwise.
    rays_per_step: int | None = Field(default=None, ge=16, le=65_536)
    occupancy_resolution: int | None = Field(default=None, ge=8, le=512)
    log2_table_size: int | None = Field(default=None, ge=10, le=22)


class EvaluateParams(_Params):
    """Score a model version on scenes with ground-truth labels (fills the R matrix)."""

    model: Ref | None = Field(default=None, description="model version (default: current)")
    scenes: list[Ref] | None = Field(
        default=None,
        min_length=1,
        max_length=1000,
        description="default: every scene labelled on all frames",
    )
    split: Literal["val", "train", "all"] = "val"


class PretrainParams(_Params):
    """Train a new segmentation network on labelled scenes; registers a new lineage root."""

    scenes: list[Ref] = Field(min_length=1, max_length=1000)
    val_scenes: list[Ref] | None = Field(default=None, max_length=1000)
    arch: str | None = Field(
        default=None, max_length=64, description="default: the light CPU network"
    )
    epochs: int = Field(default=12, ge=1, le=10_000)
    batch_size: int = Field(default=8, ge=1, le=1024)
    lr: float = Field(default=2e-3, gt=0, le=1.0)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    size: Size | None = Field(
        default=None, description="training size (default: the first scene's colour size)"
    )
    name: Name | None = Field(
        default=None, description="name of the new model version (default: pretrain-<job id>)"
    )
    lineage: Name | None = Field(
        default=None, description="name of the new lineage (default: the model name)"
    )
    make_current: bool | None = Field(
        default=None, description="default: when no model is current yet"
    )


class AdaptParams(_Params):
    """Adapt the lineage's newest model to a scene: NeRF pseudo-labels, joint training and
    replay from the memory bank (``csa_core.adapt``)."""

    scene: Ref
    model: Ref | None = Field(
        default=None,
        description="selects the lineage (default: the current model's); the job adapts that "
        "lineage's newest version when it starts",
    )
    preset: str = Field(
        default="cpu",
        max_length=32,
        description="adaptation preset of csa_core.adapt: paper, cpu or tiny",
    )
    mode: Literal["joint", "ni_nl", "gi_nl"] | None = Field(
        default=None, description="default: the preset's (joint training)"
    )
    seed: int = Field(
        default=0,
        ge=0,
        le=2**31 - 1,
        description="seed of every random step (NeRF, fine-tuning, replay), as csa adapt --seed",
    )
    make_current: bool = True


class FitNerfJob(BaseModel):
    kind: Literal["fit_nerf"]
    params: FitNerfParams


class EvaluateJob(BaseModel):
    kind: Literal["evaluate"]
    params: EvaluateParams = Field(default_factory=EvaluateParams)


class PretrainJob(BaseModel):
    kind: Literal["pretrain"]
    params: PretrainParams


class AdaptJob(BaseModel):
    kind: Literal["adapt"]
    params: AdaptParams


JobCreate = Annotated[
    FitNerfJob | EvaluateJob | PretrainJob | AdaptJob, Field(discriminator="kind")
]

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]

JobId = Annotated[int, Path(ge=1, le=MAX_ID)]  # a job's id in a route's path (/jobs/{job_id})


class JobOut(RecordOut):
    id: int
    kind: str
    status: JobStatus
    params: JsonObject
    lineage: str | None
    progress: float
    message: str
    result: dict[str, Any] | None
    error: str | None
    cancel_requested: bool
    attempts: int
    worker_id: str | None
    created_at: Timestamp
    started_at: Timestamp | None
    finished_at: Timestamp | None


class JobLogLine(BaseModel):
    time: Timestamp
    level: str
    message: str


class JobLogOut(BaseModel):
    job_id: int
    lines: list[JobLogLine]


class JobKindOut(BaseModel):
    kind: str
    description: str
    available: bool
    reason: str | None
