"""Storing validated frames: blobs in the artifact store, rows in the database, idempotently.

A frame is identified by (scene, name). Uploading the same content again returns the stored
frame unchanged; other content under a stored name is a conflict unless ``replace`` is set.
Blobs are written before the rows that refer to them, so a failure at any point leaves what
was stored before intact.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from csa_core.data.camera import Intrinsics
from server import faults
from server.artifacts import ArtifactStore
from server.db.models import MAX_ID, Frame, Scene
from server.errors import conflict, invalid
from server.frame_validation import SceneCamera, ValidFrame


@dataclass(frozen=True)
class StoreOutcome:
    frame: Frame
    created: bool
    replaced: bool = False


def scene_camera(scene: Scene) -> SceneCamera:
    return SceneCamera(
        intrinsics=Intrinsics.from_dict(scene.intrinsics) if scene.intrinsics else None,
        depth_intrinsics=Intrinsics.from_dict(scene.depth_intrinsics)
        if scene.depth_intrinsics
        else None,
        depth_size=(scene.depth_width, scene.depth_height)
        if scene.depth_width and scene.depth_height
        else None,
    )


def _pose_list(pose: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(pose, dtype=np.float64)]


def content_digest(
    color_sha: str, depth_sha: str, labels_sha: str | None, pose: list[list[float]]
) -> str:
    payload = json.dumps(
        {"color": color_sha, "depth": depth_sha, "labels": labels_sha, "pose": pose}, sort_keys=True
    )
    return hashlib.sha256(payload.encode()).hexdigest()


def digest_of(frame: ValidFrame) -> str:
    """The content digest a validated frame will have once stored."""
    sha = lambda b: hashlib.sha256(b).hexdigest()  # noqa: E731
    return content_digest(
        sha(frame.color),
        sha(frame.depth),
        sha(frame.labels) if frame.labels is not None else None,
        _pose_list(frame.pose),
    )


def _order_key(session: Session, scene_id: int, name: str) -> int:
    if name.isdigit():
        return int(name)
    top = session.scalar(select(func.max(Frame.order_key)).where(Frame.scene_id == scene_id))
    # After a frame numbered MAX_ID, named frames share its key (ordered by name): the column
    # and the list's cursors hold no larger number.
    return min((top or 0) + 1, MAX_ID)


def next_frame_name(session: Session, scene_id: int) -> str:
    """The number after the scene's largest; a 422 naming ``name`` once that would pass
    :data:`MAX_ID` (the largest numeric name an upload may give)."""
    top = session.scalar(select(func.max(Frame.order_key)).where(Frame.scene_id == scene_id))
    if top is not None and top >= MAX_ID:
        raise invalid(
            "name",
            f"this scene's frame numbers reach {MAX_ID}, so there is no next number; give the "
            "frame a name",
        )
    return str(0 if top is None else top + 1)


def store_frame(
    session: Session,
    store: ArtifactStore,
    scene: Scene,
    name: str,
    frame: ValidFrame,
    replace: bool = False,
) -> StoreOutcome:
    """Store one validated frame in the session's transaction (the caller commits)."""
    digest = digest_of(frame)
    existing = session.scalar(select(Frame).where(Frame.scene_id == scene.id, Frame.name == name))
    if existing is not None and existing.content_sha256 == digest:
        return StoreOutcome(existing, created=False)
    if existing is not None and not replace:
        raise conflict(
            f"frame {name!r} of scene {scene.name!r} already exists with other content (pass "
            "replace=true to overwrite it)",
            field="name",
        )

    color = store.put_bytes(
        session, frame.color, "color", "image/jpeg" if frame.color_ext == ".jpg" else "image/png"
    )
    depth = store.put_bytes(session, frame.depth, "depth", "image/png")
    labels = (
        store.put_bytes(session, frame.labels, "labels", "image/png")
        if frame.labels is not None
        else None
    )
    faults.point("frame.blobs_written")
    if scene.intrinsics is None and frame.intrinsics is not None:
        scene.intrinsics = frame.intrinsics.to_dict()
    if scene.depth_width is None:
        scene.depth_width, scene.depth_height = frame.depth_size
    if scene.depth_intrinsics is None and frame.depth_intrinsics is not None:
        scene.depth_intrinsics = frame.depth_intrinsics.to_dict()
    pose = _pose_list(frame.pose)
    if existing is not None:
        existing.color_sha256, existing.color_ext, existing.depth_sha256 = (
            color.sha256,
            frame.color_ext,
            depth.sha256,
        )
        existing.labels_sha256 = labels.sha256 if labels else None
        existing.pose, existing.content_sha256 = pose, digest
        session.flush()
        return StoreOutcome(existing, created=False, replaced=True)
    row = Frame(
        scene_id=scene.id,
        name=name,
        order_key=_order_key(session, scene.id, name),
        color_sha256=color.sha256,
        color_ext=frame.color_ext,
        depth_sha256=depth.sha256,
        labels_sha256=labels.sha256 if labels else None,
        pose=pose,
        content_sha256=digest,
    )
    session.add(row)
    session.flush()
    return StoreOutcome(row, created=True)
