"""The service's state in numbers: whether the database answers, the workers alive, jobs by
kind and status, what is stored (``/health``, ``/metrics``)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from sqlalchemy import func, select, text
from sqlalchemy.orm import Session

from server.db.models import (
    Artifact,
    Frame,
    Job,
    ModelVersion,
    NerfCheckpoint,
    Scene,
    Worker,
    utcnow,
)
from server.settings import Settings


def check_database(db: Session) -> None:
    """Raises when the database does not answer."""
    db.execute(text("SELECT 1"))


def workers_alive(db: Session, settings: Settings) -> int:
    """Workers still running whose last heartbeat is recent (three heartbeats and a poll)."""
    horizon = utcnow() - dt.timedelta(
        seconds=3 * settings.heartbeat_seconds + settings.worker_poll_seconds + 5
    )
    alive = select(func.count(Worker.id)).where(
        Worker.stopped_at.is_(None), Worker.heartbeat_at >= horizon
    )
    return db.scalar(alive) or 0


def job_counts(db: Session) -> dict[tuple[str, str], int]:
    """(kind, status) -> number of jobs, for the pairs that have any."""
    counted = select(Job.kind, Job.status, func.count(Job.id)).group_by(Job.kind, Job.status)
    return {(k, s): n for k, s, n in db.execute(counted)}


@dataclass(frozen=True)
class Stored:
    scenes: int
    frames: int
    model_versions: int
    memory_bank_bytes: int  # the active NeRFs'
    memory_bank_scenes: int
    artifact_bytes: int


def stored(db: Session) -> Stored:
    def number(query) -> int:
        return db.scalar(query) or 0

    active = NerfCheckpoint.active.is_(True)
    bank_bytes = select(func.coalesce(func.sum(NerfCheckpoint.size_bytes), 0)).where(active)
    bank_scenes = select(func.count(func.distinct(NerfCheckpoint.scene_id))).where(active)
    return Stored(
        scenes=number(select(func.count(Scene.id))),
        frames=number(select(func.count(Frame.id))),
        model_versions=number(select(func.count(ModelVersion.id))),
        memory_bank_bytes=number(bank_bytes),
        memory_bank_scenes=number(bank_scenes),
        artifact_bytes=number(select(func.coalesce(func.sum(Artifact.size_bytes), 0))),
    )
