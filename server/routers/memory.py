"""``/api/v1/memory``: the memory bank, one Semantic-NeRF per scene with its size and quality
(``server/services/nerfs.py``)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from server.auth import OperatorScope
from server.deps import DbDep, ServicesDep
from server.schemas.common import ERROR_RESPONSES, ParamText
from server.schemas.memory import MemoryBankOut, NerfOut
from server.services import nerfs

router = APIRouter(
    prefix="/memory",
    tags=["memory bank"],
    responses=ERROR_RESPONSES,
    dependencies=[OperatorScope],
)


@router.get(
    "",
    response_model=MemoryBankOut,
    summary="the active NeRF of every scene, sizes and quality",
)
def memory_bank(db: DbDep, include_inactive: bool = False) -> MemoryBankOut:
    return nerfs.memory_bank(db, include_inactive)


@router.get("/{scene_ref}", response_model=NerfOut)
def scene_nerf(scene_ref: ParamText, db: DbDep) -> NerfOut:
    return nerfs.scene_nerf(db, scene_ref)


@router.get(
    "/{scene_ref}/download",
    responses={
        200: {
            "content": {"application/zip": {}},
            "description": "the checkpoint files (safetensors + JSON) as a zip",
        }
    },
    response_class=Response,
)
def download_nerf(scene_ref: ParamText, db: DbDep, services: ServicesDep) -> Response:
    body, filename = nerfs.nerf_zip(db, services.store, scene_ref)
    return Response(
        body,
        media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )
