"""The memory bank: one active Semantic-NeRF checkpoint per scene, with its size and quality.

A lineage's continual steps replay the NeRFs that its own earlier steps banked (the adapt
job that made each version records the NeRF it banked, whatever NeRF of that scene is active
now): :func:`lineage_nerfs` names their files on the API node, and :class:`StoredNerfMemory`
hands them to the core's step as stored, without re-saving.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from server.artifacts import ArtifactStore
from server.db.models import ModelVersion, NerfCheckpoint
from server.db.models import Scene as SceneRow
from server.jobs.phases import FileRef, existing, stored_file

if TYPE_CHECKING:
    from csa_core.nerf.model import SemanticNerf

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
    session.execute(
        update(NerfCheckpoint).where(NerfCheckpoint.scene_id == scene_id).values(active=False)
    )
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


@dataclass(frozen=True)
class StoredNerf:
    """A banked NeRF of a lineage: its scene and its checkpoint file."""

    scene_id: int
    scene: str
    file: FileRef
    size_bytes: int


def lineage_nerfs(
    session: Session,
    store: ArtifactStore,
    chain: Sequence[ModelVersion],
    exclude_scene_id: int | None = None,
) -> list[StoredNerf]:
    """The NeRFs banked by the steps of a lineage (``chain``, root first), oldest scene first,
    one per scene (a scene adapted to again keeps its first place and its newest NeRF);
    ``exclude_scene_id`` leaves that scene out. A step that banked nothing (the collapse
    guard skipped its scene) adds nothing."""
    found: dict[int, StoredNerf] = {}
    for version in chain:
        sid = version.adapted_scene_id
        if sid is None or sid == exclude_scene_id or version.job_id is None:
            continue
        nerf = session.scalar(
            select(NerfCheckpoint)
            .where(NerfCheckpoint.scene_id == sid, NerfCheckpoint.job_id == version.job_id)
            .order_by(NerfCheckpoint.id.desc())
            .limit(1)
        )
        row = session.get(SceneRow, sid)
        if nerf is None or row is None or NERF_FILE not in nerf.files:
            continue
        file = stored_file(store, nerf.files[NERF_FILE])
        found[sid] = StoredNerf(sid, row.name, file, int(nerf.size_bytes))
    return list(found.values())


class StoredNerfMemory:
    """A lineage's memory bank as the core's continual step uses it
    (``csa_core.adapt.memory_bank.NerfMemory``): earlier scenes' NeRFs read from their files
    as stored, and the NeRF a step adds written once to ``folder`` (:attr:`added`) for the
    job to register with :func:`add_nerf` when it completes."""

    def __init__(self, entries: Sequence[StoredNerf], folder: Path):
        self.entries = list(entries)
        self.folder = Path(folder)
        self.added: tuple[str, Path, int] | None = None  # (scene, file, bytes) of the new NeRF

    @property
    def scenes(self) -> list[str]:
        names = [e.scene for e in self.entries]
        if self.added is not None and self.added[0] not in names:
            names.append(self.added[0])
        return names

    def load(self, scene: str, device: str | None = "cpu") -> SemanticNerf:
        from csa_core.nerf.checkpoint import load_checkpoint

        if self.added is not None and self.added[0] == scene:
            return load_checkpoint(self.added[1], device=device)
        entry = next((e for e in self.entries if e.scene == scene), None)
        if entry is None:
            raise LookupError(
                f"no NeRF of scene {scene!r} in this lineage's memory bank (have: "
                f"{', '.join(self.scenes) or 'none'})"
            )
        return load_checkpoint(existing(entry.file), device=device)

    def add(self, scene: str, nerf: SemanticNerf) -> int:
        from csa_core.nerf.checkpoint import save_checkpoint

        path = self.folder / NERF_FILE
        size = save_checkpoint(nerf, path)
        self.added = (scene, path, int(size))
        return int(size)

    def bytes_per_scene(self) -> dict[str, int]:
        sizes = {e.scene: e.size_bytes for e in self.entries}
        if self.added is not None:
            sizes[self.added[0]] = self.added[2]
        return sizes
