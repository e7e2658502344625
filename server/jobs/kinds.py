"""The job kinds: parameters, the capability each needs, how it is queued and how it runs.

A kind is a small module with ``prepare`` (resolve the request's references into ids and
name the lineage the job belongs to, while the request is still open, so errors are 4xx)
and ``run`` (the work, through the core library's public API, under whichever executor runs
it). ``gpu`` says whether a Ray task of the kind asks for a GPU (when the cluster has any);
``inputs`` names the rows and files it reads (``server/executors/bundle.py``), which the Ray
executor ships to the task.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel
from sqlalchemy.orm import Session

from server import capabilities
from server.db.models import Job
from server.executors import bundle
from server.jobs import adapt, evaluate, fit_nerf, pretrain
from server.jobs.context import JobContext
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
    run: Callable[[JobContext], None]
    gpu: bool = False
    inputs: Callable[[Session, dict[str, Any]], bundle.JobInputs] | None = None

    def missing_reason(self) -> str | None:
        for cap in self.needs:
            reason = capabilities.missing_reason(cap)
            if reason is not None:
                return reason
        return None


KINDS: dict[str, JobKind] = {
    k.name: k
    for k in (
        JobKind("fit_nerf", "fit a Semantic-NeRF to a scene and keep it in the memory bank", FitNerfParams, ("nerf",), fit_nerf.prepare, fit_nerf.run, True, bundle.fit_nerf_inputs),
        JobKind("evaluate", "score a model version on labelled scenes (R matrix entries)", EvaluateParams, ("seg",), evaluate.prepare, evaluate.run, False, bundle.evaluate_inputs),
        JobKind("pretrain", "train a new segmentation network on labelled scenes", PretrainParams, ("seg",), pretrain.prepare, pretrain.run, True, bundle.pretrain_inputs),
        JobKind("adapt", "adapt the lineage's newest model to a scene (continual step)", AdaptParams, ("adapt", "seg", "nerf"), adapt.prepare, adapt.run, True, bundle.adapt_inputs),
    )
}


def runnable_kinds() -> set[str]:
    return {name for name, kind in KINDS.items() if kind.missing_reason() is None}
