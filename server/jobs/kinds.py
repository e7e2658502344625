"""The job kinds: parameters, the capability each needs, how it is queued and how it runs.

A kind is a small module with ``prepare`` (resolve the request's references into ids and
name the lineage the job belongs to, while the request is still open, so errors are 4xx) and
the three phases every executor runs (``server/jobs/phases.py``): ``gather`` the inputs from
the database, ``compute`` through the core library's public API, ``register`` the outputs.
``gpu`` says whether a Ray task of the kind asks for a GPU (when the cluster has any).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel
from sqlalchemy.orm import Session

from server import capabilities
from server.db.models import Job
from server.jobs import adapt, evaluate, fit_nerf, pretrain
from server.jobs.phases import Compute, Gather, Register
from server.schemas.jobs import AdaptParams, EvaluateParams, FitNerfParams, PretrainParams

# prepare(session, params, job) -> (params with references resolved to ids, lineage or None)
Prepare = Callable[[Session, Any, Job], tuple[dict[str, Any], str | None]]


@dataclass(frozen=True)
class JobKind:
    name: str
    description: str
    params: type[BaseModel]
    needs: tuple[str, ...]
    prepare: Prepare
    gather: Gather
    compute: Compute  # a module-level function: a Ray task imports it by name
    register: Register
    gpu: bool = False

    def missing_reason(self) -> str | None:
        for cap in self.needs:
            reason = capabilities.missing_reason(cap)
            if reason is not None:
                return reason
        return None


KINDS: dict[str, JobKind] = {
    k.name: k
    for k in (
        JobKind(
            "fit_nerf",
            "fit a Semantic-NeRF to a scene and keep it in the memory bank",
            FitNerfParams,
            ("nerf",),
            fit_nerf.prepare,
            fit_nerf.gather,
            fit_nerf.compute,
            fit_nerf.register,
            gpu=True,
        ),
        JobKind(
            "evaluate",
            "score a model version on labelled scenes (R matrix entries)",
            EvaluateParams,
            ("seg",),
            evaluate.prepare,
            evaluate.gather,
            evaluate.compute,
            evaluate.register,
            gpu=False,
        ),
        JobKind(
            "pretrain",
            "train a new segmentation network on labelled scenes",
            PretrainParams,
            ("seg",),
            pretrain.prepare,
            pretrain.gather,
            pretrain.compute,
            pretrain.register,
            gpu=True,
        ),
        JobKind(
            "adapt",
            "adapt the lineage's newest model to a scene (continual step)",
            AdaptParams,
            ("adapt", "seg", "nerf"),
            adapt.prepare,
            adapt.gather,
            adapt.compute,
            adapt.register,
            gpu=True,
        ),
    )
}


def runnable_kinds() -> set[str]:
    return {name for name, kind in KINDS.items() if kind.missing_reason() is None}
