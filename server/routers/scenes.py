"""``/api/v1/scenes``: create, list, show and delete scenes (``server/services/scenes.py``)."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from server.auth import DeviceScope, OperatorScope, PrincipalDep, SceneAccess
from server.deps import DbDep, ServicesDep
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.schemas.common import ERROR_RESPONSES, ParamText
from server.schemas.scenes import SceneCreate, SceneOut
from server.services import scenes

# Device keys create scenes and see only their own (server/auth.py); deleting needs operator.
router = APIRouter(
    prefix="/scenes", tags=["scenes"], responses=ERROR_RESPONSES, dependencies=[DeviceScope]
)


@router.post(
    "",
    response_model=SceneOut,
    status_code=status.HTTP_201_CREATED,
    responses={409: ERROR_RESPONSES[422]},
)
def create_scene(body: SceneCreate, db: DbDep, principal: PrincipalDep) -> SceneOut:
    return scenes.create_scene(db, body.name, body.description, principal.key_id)


@router.get("", response_model=list[SceneOut], responses=PAGE_RESPONSES)
def list_scenes(
    db: DbDep, response: Response, pages: PageDep, principal: PrincipalDep
) -> list[SceneOut]:
    """Scenes by id, a page at a time; ``X-Total-Count`` is the number of all scenes (a device
    key's: of the scenes it created)."""
    rows = page(db, scenes.scenes_query(principal), pages, response, scenes.ORDER)
    return [scenes.scene_out(db, s) for s in rows]


@router.get("/{scene_ref}", response_model=SceneOut, dependencies=[SceneAccess])
def show_scene(scene_ref: ParamText, db: DbDep) -> SceneOut:
    return scenes.show_scene(db, scene_ref)


@router.delete(
    "/{scene_ref}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={409: ERROR_RESPONSES[422]},
    dependencies=[OperatorScope],
)
def delete_scene(scene_ref: ParamText, db: DbDep, services: ServicesDep) -> Response:
    """Delete a scene, its frames and its NeRFs; refused while a job for it is queued or running."""
    scenes.delete_scene(db, services.store, scene_ref)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
