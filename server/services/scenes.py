"""Scenes: create, list, show and delete (``/api/v1/scenes``, the dashboard's scene pages)."""

from __future__ import annotations

from sqlalchemy import Select, false, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.artifacts import ArtifactStore
from server.db.models import Frame, Job, NerfCheckpoint, Scene
from server.errors import conflict
from server.jobs.queue import QUEUED, RUNNING
from server.keys import OPERATOR, Principal
from server.lookups import get_scene
from server.schemas.common import IntrinsicsOut
from server.schemas.scenes import SceneOut

ORDER = (Scene.id,)  # the sort key of :func:`scenes_query`, for its pages (server/pagination.py)


def scene_out(db: Session, scene: Scene) -> SceneOut:
    n, labelled = db.execute(
        select(func.count(Frame.id), func.count(Frame.labels_sha256)).where(
            Frame.scene_id == scene.id
        )
    ).one()
    active = select(NerfCheckpoint.id).where(
        NerfCheckpoint.scene_id == scene.id, NerfCheckpoint.active.is_(True)
    )
    has_nerf = db.scalar(active.limit(1)) is not None
    return SceneOut(
        id=scene.id,
        name=scene.name,
        description=scene.description,
        intrinsics=IntrinsicsOut(**scene.intrinsics) if scene.intrinsics else None,
        depth_size=(scene.depth_width, scene.depth_height)
        if scene.depth_width and scene.depth_height
        else None,
        num_frames=int(n),
        num_labelled_frames=int(labelled),
        has_nerf=has_nerf,
        created_at=scene.created_at,
    )


def create_scene(
    db: Session, name: str, description: str | None, owner_key_id: int | None
) -> SceneOut:
    """A new scene owned by the key ``owner_key_id`` (None: a settings key); 409 when the
    name is taken."""
    if db.scalar(select(Scene.id).where(Scene.name == name)) is not None:
        raise conflict(f"scene {name!r} exists", field="name")
    scene = Scene(name=name, description=description, owner_key_id=owner_key_id)
    db.add(scene)
    try:
        db.commit()
    except IntegrityError:
        db.rollback()
        raise conflict(f"scene {name!r} exists", field="name") from None
    return scene_out(db, scene)


def scenes_query(visible_to: Principal | None = None) -> Select:
    """Scenes by id; for a device key only the ones it created."""
    query = select(Scene).order_by(*ORDER)
    if visible_to is not None and not visible_to.allows(OPERATOR):
        if visible_to.key_id is None:
            return query.where(false())
        query = query.where(Scene.owner_key_id == visible_to.key_id)
    return query


def all_scenes(db: Session, visible_to: Principal | None = None) -> list[SceneOut]:
    """Every scene ``visible_to`` sees, by id: for the dashboard, which shows them all (the
    route answers pages)."""
    return [scene_out(db, s) for s in db.scalars(scenes_query(visible_to))]


def show_scene(db: Session, scene_ref: str | int) -> SceneOut:
    """A scene by id or name; 404 otherwise."""
    return scene_out(db, get_scene(db, scene_ref))


def delete_scene(db: Session, store: ArtifactStore, scene_ref: str) -> None:
    """Delete a scene, its frames and its NeRFs, and the stored files nothing else uses;
    refused (409) while a job for it is queued or running."""
    scene = get_scene(db, scene_ref)
    for job in db.scalars(select(Job).where(Job.status.in_([QUEUED, RUNNING]))):
        p = job.params or {}
        if (
            p.get("scene_id") == scene.id
            or scene.id in (p.get("scene_ids") or [])
            or scene.id in (p.get("val_scene_ids") or [])
        ):
            raise conflict(
                f"job {job.id} ({job.kind}, {job.status}) uses this scene; cancel it first"
            )
    db.delete(scene)
    db.flush()
    removed = store.collect_garbage(db)
    db.commit()
    store.remove_unrecorded(db, removed)  # older leftovers: the background sweep
