"""``/api/v1/memory``: the memory bank, one Semantic-NeRF per scene with its size and quality."""

from __future__ import annotations

import io
import zipfile

from fastapi import APIRouter, Response
from sqlalchemy import select

from server.auth import OperatorScope
from server.db.models import NerfCheckpoint, Scene
from server.deps import DbDep, ServicesDep
from server.errors import not_found
from server.lookups import active_nerf, get_scene
from server.schemas.common import ERROR_RESPONSES
from server.schemas.memory import MemoryBankOut, NerfOut

router = APIRouter(prefix="/memory", tags=["memory bank"], responses=ERROR_RESPONSES, dependencies=[OperatorScope])


def nerf_out(n: NerfCheckpoint, scene_name: str) -> NerfOut:
    return NerfOut(
        id=n.id,
        scene_id=n.scene_id,
        scene=scene_name,
        job_id=n.job_id,
        size_bytes=n.size_bytes,
        preset=n.preset,
        labels_source=n.labels_source,
        quality=n.quality,
        active=n.active,
        created_at=n.created_at,
    )


@router.get("", response_model=MemoryBankOut, summary="the active NeRF of every scene, sizes and quality")
def memory_bank(db: DbDep, include_inactive: bool = False) -> MemoryBankOut:
    q = select(NerfCheckpoint, Scene.name).join(Scene, Scene.id == NerfCheckpoint.scene_id).order_by(NerfCheckpoint.scene_id, NerfCheckpoint.id)
    if not include_inactive:
        q = q.where(NerfCheckpoint.active.is_(True))
    entries = [nerf_out(n, name) for n, name in db.execute(q)]
    active = [e for e in entries if e.active]
    return MemoryBankOut(entries=entries, total_bytes=sum(e.size_bytes for e in active), num_scenes=len({e.scene_id for e in active}))


@router.get("/{scene_ref}", response_model=NerfOut)
def scene_nerf(scene_ref: str, db: DbDep) -> NerfOut:
    scene = get_scene(db, scene_ref)
    nerf = active_nerf(db, scene.id)
    if nerf is None:
        raise not_found("NeRF of scene", scene.name)
    return nerf_out(nerf, scene.name)


@router.get(
    "/{scene_ref}/download",
    responses={200: {"content": {"application/zip": {}}, "description": "the checkpoint files (safetensors + JSON) as a zip"}},
    response_class=Response,
)
def download_nerf(scene_ref: str, db: DbDep, services: ServicesDep) -> Response:
    scene = get_scene(db, scene_ref)
    nerf = active_nerf(db, scene.id)
    if nerf is None:
        raise not_found("NeRF of scene", scene.name)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for name, sha in sorted(nerf.files.items()):
            zf.write(services.store.open_verified(sha), arcname=name)
    return Response(buf.getvalue(), media_type="application/zip", headers={"Content-Disposition": f'attachment; filename="{scene.name}-nerf.zip"'})
