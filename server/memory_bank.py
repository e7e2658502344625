"""The memory bank: one active Semantic-NeRF checkpoint per scene, with its size and quality."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy import update
from sqlalchemy.orm import Session

from server.artifacts import ArtifactStore
from server.db.models import NerfCheckpoint

NERF_FILE = "nerf.safetensors"


def add_nerf(
    session: Session,
    store: ArtifactStore,
    scene_id: int,
    checkpoint: Path,
    *,
    job_id: int | None,
    preset: str,
    labels_source: str,
    quality: dict[str, Any],
) -> NerfCheckpoint:
    """Store a NeRF checkpoint file (safetensors with its JSON metadata) and make it the
    scene's active NeRF."""
    stored = store.put_file(session, checkpoint, "nerf")
    files, size = {NERF_FILE: stored.sha256}, stored.size_bytes
    session.execute(update(NerfCheckpoint).where(NerfCheckpoint.scene_id == scene_id).values(active=False))
    entry = NerfCheckpoint(
        scene_id=scene_id,
        job_id=job_id,
        files=files,
        size_bytes=size,
        preset=preset,
        labels_source=labels_source,
        quality=quality,
        active=True,
    )
    session.add(entry)
    session.flush()
    return entry
