"""``/api/v1/scenes``: create, list, show and delete scenes."""

from __future__ import annotations

from fastapi import APIRouter, Response, status
from sqlalchemy import Select, false, func, select
from sqlalchemy.exc import IntegrityError

from server.auth import DeviceScope, OperatorScope, PrincipalDep, SceneAccess
from server.db.models import Frame, Job, NerfCheckpoint, Scene
from server.deps import DbDep, ServicesDep
from server.errors import conflict
from server.jobs.queue import QUEUED, RUNNING
from server.keys import OPERATOR, Principal
from server.lookups import get_scene
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.schemas.common import ERROR_RESPONSES, IntrinsicsOut
from server.schemas.scenes import SceneCreate, SceneOut

# Device keys create scenes and see only their own (server/auth.py); deleting needs operator.
router = APIRouter(prefix="/scenes", tags=["scenes"], responses=ERROR_RESPONSES, dependencies=[DeviceScope])


def scene_out(db, scene: Scene) -> SceneOut:
    n, labelled = db.execute(select(func.count(Frame.id), func.count(Frame.labels_sha256)).where(Frame.scene_id == scene.id)).one()
    has_nerf = db.scalar(select(NerfCheckpoint.id).where(NerfCheckpoint.scene_id == scene.id, NerfCheckpoint.active.is_(True)).limit(1)) is not None
    return SceneOut(
        id=scene.id,
        name=scene.name,
        description=scene.description,
        intrinsics=IntrinsicsOut(**scene.intrinsics) if scene.intrinsics else None,
        depth_size=(scene.depth_width, scene.depth_height) if scene.depth_width and scene.depth_height else None,
        num_frames=int(n),
        num_labelled_frames=int(labelled),
        has_nerf=has_nerf,
        created_at=scene.created_at,
    )


@router.post("", response_model=SceneOut, status_code=status.HTTP_201_CREATED, responses={409: ERROR_RESPONSES[422]})
def create_scene(body: SceneCreate, db: DbDep, principal: PrincipalDep) -> SceneOut:
    if db.scalar(select(Scene.id).where(Scene.name == body.name)) is not None:
        raise conflict(f"scene {body.name!r} exists", field="name")
    scene = Scene(name=body.name, description=body.description, owner_key_id=principal.key_id)
    db.add(scene)
    try:
        db.commit()
    except IntegrityError:
        db.rollback()
        raise conflict(f"scene {body.name!r} exists", field="name") from None
    return scene_out(db, scene)


def scenes_query(visible_to: Principal | None = None) -> Select:
    """Scenes by id; for a device key only the ones it created."""
    query = select(Scene).order_by(Scene.id)
    if visible_to is not None and not visible_to.allows(OPERATOR):
        query = query.where(Scene.owner_key_id == visible_to.key_id) if visible_to.key_id is not None else query.where(false())
    return query


def all_scenes(db, visible_to: Principal | None = None) -> list[SceneOut]:
    """Every scene ``visible_to`` sees, by id: for the dashboard, which shows them all (the
    route answers pages)."""
    return [scene_out(db, s) for s in db.scalars(scenes_query(visible_to))]


@router.get("", response_model=list[SceneOut], responses=PAGE_RESPONSES)
def list_scenes(db: DbDep, response: Response, pages: PageDep, principal: PrincipalDep) -> list[SceneOut]:
    """Scenes by id, a page at a time; ``X-Total-Count`` is the number of all scenes (a device
    key's: of the scenes it created)."""
    return [scene_out(db, s) for s in page(db, scenes_query(principal), pages, response, (Scene.id,))]


@router.get("/{scene_ref}", response_model=SceneOut, dependencies=[SceneAccess])
def show_scene(scene_ref: str, db: DbDep) -> SceneOut:
    return scene_out(db, get_scene(db, scene_ref))


@router.delete("/{scene_ref}", status_code=status.HTTP_204_NO_CONTENT, responses={409: ERROR_RESPONSES[422]}, dependencies=[OperatorScope])
def delete_scene(scene_ref: str, db: DbDep, services: ServicesDep) -> Response:
    """Delete a scene, its frames and its NeRFs; refused while a job for it is queued or running."""
    scene = get_scene(db, scene_ref)
    for job in db.scalars(select(Job).where(Job.status.in_([QUEUED, RUNNING]))):
        p = job.params or {}
        if p.get("scene_id") == scene.id or scene.id in (p.get("scene_ids") or []) or scene.id in (p.get("val_scene_ids") or []):
            raise conflict(f"job {job.id} ({job.kind}, {job.status}) uses this scene; cancel it first")
    db.delete(scene)
    db.flush()
    removed = services.store.collect_garbage(db)
    db.commit()
    services.store.remove_unrecorded(db, removed)  # older leftovers: the background sweep
    return Response(status_code=status.HTTP_204_NO_CONTENT)
