"""Finding rows by the references clients use: numeric ids or names (``current`` for models)."""

from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db.models import MAX_ID, Job, ModelVersion, NerfCheckpoint, Scene
from server.errors import APIError, invalid, not_found


def _as_id(ref: str | int) -> int | None:
    if isinstance(ref, int):
        return ref
    ident = int(ref) if ref.isascii() and ref.isdigit() and len(ref) <= 10 else None
    return ident if ident is not None and ident <= MAX_ID else None


def get_scene(session: Session, ref: str | int) -> Scene:
    """A scene by id or by name; 404 otherwise."""
    ident = _as_id(ref)
    scene = (
        session.get(Scene, ident)
        if ident is not None
        else session.scalar(select(Scene).where(Scene.name == str(ref)))
    )
    if scene is None:
        raise not_found("scene", ref)
    return scene


def get_scenes(session: Session, refs: Sequence[str | int], field: str) -> list[Scene]:
    """Scenes by id or name, each once: a scene named twice (by any mix of ids and names) is a
    422 naming ``field``, since a job would read it twice; 404 for an unknown one."""
    scenes: list[Scene] = []
    for ref in refs:
        scene = get_scene(session, ref)
        if any(s.id == scene.id for s in scenes):
            raise invalid(field, f"scene {scene.name!r} is listed twice")
        scenes.append(scene)
    return scenes


def require_ground_truth(session: Session, scene: Scene, field: str) -> Scene:
    """``scene`` when every frame has ground-truth labels, else a 422 naming ``field``."""
    from server.scene_folders import missing_ground_truth

    problem = missing_ground_truth(session, scene)
    if problem is not None:
        raise invalid(field, f"scene {scene.name!r} {problem}")
    return scene


def current_model(session: Session, lineage: str | None = None) -> ModelVersion | None:
    """The version marked current, or with ``lineage`` the newest version of that lineage."""
    if lineage is not None:
        return session.scalar(
            select(ModelVersion)
            .where(ModelVersion.lineage == lineage)
            .order_by(ModelVersion.id.desc())
            .limit(1)
        )
    return session.scalar(select(ModelVersion).where(ModelVersion.is_current.is_(True)).limit(1))


def get_model(session: Session, ref: str | int | None) -> ModelVersion:
    """A model version by id, name or ``current`` (also for ``None``); 404 otherwise."""
    if ref is None or ref == "current":
        model = current_model(session)
        if model is None:
            raise APIError(
                404,
                "not_found",
                "no current model version: "
                "register one (POST /api/v1/models) or run a pretrain job",
            )
        return model
    ident = _as_id(ref)
    model = (
        session.get(ModelVersion, ident)
        if ident is not None
        else session.scalar(select(ModelVersion).where(ModelVersion.name == str(ref)))
    )
    if model is None:
        raise not_found("model version", ref)
    return model


def get_job(session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise not_found("job", job_id)
    return job


def active_nerf(session: Session, scene_id: int) -> NerfCheckpoint | None:
    return session.scalar(
        select(NerfCheckpoint)
        .where(NerfCheckpoint.scene_id == scene_id, NerfCheckpoint.active.is_(True))
        .order_by(NerfCheckpoint.id.desc())
        .limit(1)
    )
