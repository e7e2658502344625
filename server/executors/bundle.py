"""The inputs of a job that runs away from the database and the artifact store.

A Ray task gets no database credentials and no shared disk. Before it is submitted, the API
node reads what the job will read: the database rows (scenes, frames, model versions, NeRF
checkpoints, evaluations) into a :class:`JobInputs`, and the files those rows point to
(frames, checkpoints, NeRFs) from the artifact store. On the worker, :func:`open_snapshot`
loads the rows into an in-memory SQLite database with the service's own schema, so the job
function's ``ctx.session()`` queries run unchanged; the files become a local artifact store.

Each job kind names what it reads with one function here (``JobKind.inputs`` in
``server/jobs/kinds.py``). It over-approximates the rows (they are small) and is exact about
files (they are large): a file a job reads that its function did not name fails that job
with ``ArtifactMissing``, which the Ray executor's tests would show.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import create_engine, select
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import StaticPool

from server.db.models import Base, Evaluation, Frame, ModelVersion, NerfCheckpoint
from server.db.models import Scene as SceneRow
from server.memory_bank import lineage_nerfs
from server.registry import lineage_chain


@dataclass
class JobInputs:
    """Database rows (table name -> primary key -> column values) and artifact checksums."""

    rows: dict[str, dict[tuple[Any, ...], dict[str, Any]]] = field(default_factory=dict)
    blobs: set[str] = field(default_factory=set)

    def add(self, session: Session, model: type[Base], where: Any) -> list[dict[str, Any]]:
        """Copy the rows of ``model``'s table that match ``where``; returns them."""
        table = model.__table__
        keys = [c.name for c in table.primary_key.columns]
        found = [dict(r._mapping) for r in session.execute(select(table).where(where))]
        bucket = self.rows.setdefault(table.name, {})
        for row in found:
            bucket[tuple(row[k] for k in keys)] = row
        return found

    def table_rows(self) -> dict[str, list[dict[str, Any]]]:
        return {name: list(rows.values()) for name, rows in self.rows.items()}

    def files(self, shas: Iterable[str | None]) -> None:
        self.blobs.update(s for s in shas if s)


def add_scenes(session: Session, inputs: JobInputs, scene_ids: Iterable[int], files: bool = True) -> dict[int, bool]:
    """Scenes with their frames and (``files``) the frames' files: colour, depth, ground truth.
    Returns whether each scene has ground truth on every frame."""
    ids = sorted(set(scene_ids))
    inputs.add(session, SceneRow, SceneRow.id.in_(ids))
    labelled = dict.fromkeys(ids, False)
    frames = inputs.add(session, Frame, Frame.scene_id.in_(ids))
    for sid in ids:
        mine = [f for f in frames if f["scene_id"] == sid]
        labelled[sid] = bool(mine) and all(f["labels_sha256"] for f in mine)
    if files:
        for f in frames:
            inputs.files((f["color_sha256"], f["depth_sha256"], f["labels_sha256"]))
    return labelled


def add_models(session: Session, inputs: JobInputs, model_ids: Iterable[int]) -> None:
    """Model versions with all their files (checkpoint, BatchNorm memory)."""
    for m in inputs.add(session, ModelVersion, ModelVersion.id.in_(sorted(set(model_ids)))):
        inputs.files((m["files"] or {}).values())


def fit_nerf_inputs(session: Session, params: dict[str, Any]) -> JobInputs:
    inputs = JobInputs()
    add_scenes(session, inputs, [params["scene_id"]])
    if params.get("model_id") is not None:
        add_models(session, inputs, [params["model_id"]])
    return inputs


def pretrain_inputs(session: Session, params: dict[str, Any]) -> JobInputs:
    inputs = JobInputs()
    add_scenes(session, inputs, [*params["scene_ids"], *params.get("val_scene_ids", [])])
    return inputs


def evaluate_inputs(session: Session, params: dict[str, Any]) -> JobInputs:
    inputs = JobInputs()
    add_models(session, inputs, [params["model_id"]])
    add_scenes(session, inputs, params["scene_ids"])
    return inputs


def adapt_inputs(session: Session, params: dict[str, Any]) -> JobInputs:
    """A continual step reads its lineage: every version's row (to find the chain), the files
    of the root and the newest version, the scene and the root's pre-training scenes, the
    scenes adapted to earlier (their frames' files only when they have ground truth to score
    on), their NeRF rows and the NeRFs the lineage banked, and the lineage's evaluations."""
    inputs = JobInputs()
    versions = inputs.add(session, ModelVersion, ModelVersion.lineage == params["lineage"])
    chain = lineage_chain(session, params["lineage"])
    read = {params["scene_id"]}
    earlier = {v["adapted_scene_id"] for v in versions if v["adapted_scene_id"] is not None} - read
    if chain:
        add_models(session, inputs, [chain[0].id, chain[-1].id])
        read |= {int(i) for i in (chain[0].meta or {}).get("scene_ids", [])}
        inputs.files(n.sha256 for n in lineage_nerfs(session, chain[1:]))
    add_scenes(session, inputs, read)
    labelled = add_scenes(session, inputs, earlier - read, files=False)
    add_scenes(session, inputs, [sid for sid, yes in labelled.items() if yes])
    scene_ids = sorted(read | earlier)
    inputs.add(session, NerfCheckpoint, NerfCheckpoint.scene_id.in_(scene_ids))
    inputs.add(session, Evaluation, Evaluation.model_version_id.in_([v["id"] for v in versions]))
    return inputs


def open_snapshot(rows: dict[str, list[dict[str, Any]]]) -> sessionmaker[Session]:
    """An in-memory SQLite database with the service's schema holding ``rows`` (foreign keys
    are not enforced: the snapshot holds only the rows a job reads)."""
    engine = create_engine("sqlite://", poolclass=StaticPool, connect_args={"check_same_thread": False})
    Base.metadata.create_all(engine)
    with engine.begin() as conn:
        for table in Base.metadata.sorted_tables:
            if rows.get(table.name):
                conn.execute(table.insert(), rows[table.name])
    return sessionmaker(bind=engine, expire_on_commit=False)
