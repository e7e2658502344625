"""The model registry: segmentation checkpoints as versions with lineage, metrics and a current one.

A version's ``files`` map file names to checksums in the artifact store: always the checkpoint
(``model.safetensors``) and, for a version made by a continual step that pools BatchNorm
statistics, the lineage's per-scene BatchNorm memory after that step
(``batchnorm_memory.safetensors``, ``csa_core.adapt.bn_memory``), which the next step loads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from server.artifacts import ArtifactStore
from server.db.models import Job, ModelVersion
from server.jobs.queue import QUEUED, RUNNING

CHECKPOINT_FILE = "model.safetensors"
BATCHNORM_FILE = "batchnorm_memory.safetensors"


def set_current(session: Session, model: ModelVersion) -> None:
    session.execute(
        update(ModelVersion).where(ModelVersion.id != model.id).values(is_current=False)
    )
    model.is_current = True
    session.flush()


def register_checkpoint(
    session: Session,
    store: ArtifactStore,
    checkpoint: Path,
    *,
    name: str,
    lineage: str,
    arch: str,
    parent_id: int | None = None,
    adapted_scene_id: int | None = None,
    job_id: int | None = None,
    metrics: dict[str, Any] | None = None,
    meta: dict[str, Any] | None = None,
    make_current: bool | None = None,
    extra_files: dict[str, Path] | None = None,
) -> ModelVersion:
    """Store a checkpoint file and add its version; ``make_current=None`` makes it current
    only when no version is current yet. ``extra_files`` (file name -> path, e.g.
    :data:`BATCHNORM_FILE`) are stored beside it in the version's files."""
    stored = store.put_file(session, checkpoint, "model")
    files = {CHECKPOINT_FILE: stored.sha256}
    for file_name, path in (extra_files or {}).items():
        if file_name == CHECKPOINT_FILE:
            raise ValueError(f"register_checkpoint: {CHECKPOINT_FILE} is the checkpoint itself")
        files[file_name] = store.put_file(session, path, "model").sha256
    model = ModelVersion(
        name=name,
        lineage=lineage,
        parent_id=parent_id,
        adapted_scene_id=adapted_scene_id,
        job_id=job_id,
        arch=arch,
        files=files,
        size_bytes=stored.size_bytes,
        metrics=metrics or {},
        meta=meta or {},
        is_current=False,
    )
    session.add(model)
    session.flush()
    has_current = (
        session.scalar(select(ModelVersion.id).where(ModelVersion.is_current.is_(True)).limit(1))
        is not None
    )
    if make_current or (make_current is None and not has_current):
        set_current(session, model)
    return model


def checkpoint_sha(model: ModelVersion) -> str:
    return model.files[CHECKPOINT_FILE]


def lineage_chain(session: Session, lineage: str) -> list[ModelVersion]:
    """The versions of a lineage from its root along the newest child at each step."""
    versions = session.scalars(
        select(ModelVersion).where(ModelVersion.lineage == lineage).order_by(ModelVersion.id)
    ).all()
    if not versions:
        return []
    by_parent: dict[int | None, list[ModelVersion]] = {}
    ids = {v.id for v in versions}
    for v in versions:
        parent = v.parent_id if v.parent_id in ids else None
        by_parent.setdefault(parent, []).append(v)
    chain = [by_parent[None][0]]
    while children := by_parent.get(chain[-1].id):
        chain.append(children[-1])
    return chain


def root_conflict(
    session: Session, name: str, lineage: str, starter: str
) -> tuple[str, str] | None:
    """``(field, problem)`` when a new lineage's root version named ``name`` cannot be made:
    a version holds the name (field ``name``) or ``lineage`` exists (field ``lineage``;
    ``starter``, e.g. "a pre-training", names what starts lineages in the message), or a
    queued or running pre-training will take either when it ends (:func:`_pending_root`)."""
    if session.scalar(select(ModelVersion.id).where(ModelVersion.name == name)) is not None:
        return "name", f"a model version named {name!r} exists"
    if session.scalar(select(ModelVersion.id).where(ModelVersion.lineage == lineage)) is not None:
        return "lineage", f"lineage {lineage!r} exists; {starter} starts a new lineage"
    return _pending_root(session, name, lineage)


def _pending_root(session: Session, name: str, lineage: str) -> tuple[str, str] | None:
    """``(field, problem)`` when a queued or running pre-training will register a version
    named ``name`` (field ``name``) or the root of ``lineage`` (field ``lineage``) once it
    ends: the registry does not hold them yet, but taking them meanwhile would make a second
    root of the lineage, or fail that job on the name after all its training."""
    active = (
        select(Job)
        .where(Job.kind == "pretrain", Job.status.in_((QUEUED, RUNNING)))
        .order_by(Job.id)
    )
    for job in session.scalars(active):
        if (job.params or {}).get("name") == name:
            return (
                "name",
                f"job {job.id} ({job.status}) "
                f"registers a model version named {name!r} when it ends",
            )
        if job.lineage == lineage:
            return "lineage", f"job {job.id} ({job.status}) starts lineage {lineage!r} when it ends"
    return None
