"""NeRFs: the memory bank (one active Semantic-NeRF per scene, with its size and quality) and
the NeRF and camera a render uses (``/api/v1/memory``, ``/api/v1/scenes/{scene}/render``, the
dashboard's scene, memory and frame pictures). Adding NeRFs to the bank is
``server/memory_bank.py``'s, shared with the jobs that fit them."""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from csa_core.data.camera import Intrinsics
from server.artifacts import ArtifactStore
from server.db.models import NerfCheckpoint, Scene
from server.errors import invalid, not_found
from server.lookups import active_nerf, get_scene
from server.schemas.memory import MemoryBankOut, NerfOut

# A view holds class scores for every pixel: renders are refused above this many pixels (the
# dashboard's frame pictures are rendered smaller instead, server/ui/panels.py).
MAX_RENDER_PIXELS = 1024 * 1024


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


def memory_bank(db: Session, include_inactive: bool = False) -> MemoryBankOut:
    """The active NeRF of every scene (and with ``include_inactive`` the replaced ones), by
    scene; the sizes and the number of scenes count the active ones."""
    q = (
        select(NerfCheckpoint, Scene.name)
        .join(Scene, Scene.id == NerfCheckpoint.scene_id)
        .order_by(NerfCheckpoint.scene_id, NerfCheckpoint.id)
    )
    if not include_inactive:
        q = q.where(NerfCheckpoint.active.is_(True))
    entries = [nerf_out(n, name) for n, name in db.execute(q)]
    active = [e for e in entries if e.active]
    return MemoryBankOut(
        entries=entries,
        total_bytes=sum(e.size_bytes for e in active),
        num_scenes=len({e.scene_id for e in active}),
    )


def active_nerf_out(db: Session, scene_id: int, scene_name: str) -> NerfOut | None:
    """The scene's active NeRF, or None when it has none."""
    nerf = active_nerf(db, scene_id)
    return nerf_out(nerf, scene_name) if nerf is not None else None


def _active_nerf_of(db: Session, scene_ref: str) -> tuple[Scene, NerfCheckpoint]:
    scene = get_scene(db, scene_ref)
    nerf = active_nerf(db, scene.id)
    if nerf is None:
        raise not_found("NeRF of scene", scene.name)
    return scene, nerf


def scene_nerf(db: Session, scene_ref: str) -> NerfOut:
    """The active NeRF of a scene by id or name; 404 for an unknown scene or one without."""
    scene, nerf = _active_nerf_of(db, scene_ref)
    return nerf_out(nerf, scene.name)


def nerf_zip(db: Session, store: ArtifactStore, scene_ref: str) -> tuple[bytes, str]:
    """The files of a scene's active NeRF (safetensors and JSON) as a zip, and its file name."""
    scene, nerf = _active_nerf_of(db, scene_ref)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for name, sha in sorted(nerf.files.items()):
            zf.write(store.open_verified(sha), arcname=name)
    return buf.getvalue(), f"{scene.name}-nerf.zip"


# -- rendering -------------------------------------------------------------------------------


@dataclass(frozen=True)
class NerfFiles:
    """What loading a NeRF needs (``server/nerf_cache.py``): its id and its files (file name
    -> checksum in the artifact store)."""

    id: int
    files: dict[str, str]


def active_nerf_files(db: Session, scene_id: int) -> NerfFiles | None:
    """The files of the scene's active NeRF, or None when it has none."""
    nerf = active_nerf(db, scene_id)
    return NerfFiles(nerf.id, dict(nerf.files)) if nerf is not None else None


@dataclass(frozen=True)
class RenderTarget:
    """A render's scene, NeRF and camera, read before the request's session closes."""

    scene_id: int
    nerf: NerfFiles
    camera: Intrinsics


def render_target(
    db: Session, scene_ref: str, nerf_id: int | None, camera: Intrinsics | None
) -> RenderTarget:
    """The NeRF to render a scene with (``nerf_id``, one of the scene's, or its active one)
    and the camera (``camera``, or the scene's); 404 for an unknown scene or NeRF, 422 without
    a camera or for one of more than :data:`MAX_RENDER_PIXELS`."""
    scene = get_scene(db, scene_ref)
    if nerf_id is not None:
        nerf = db.get(NerfCheckpoint, nerf_id)
        if nerf is None or nerf.scene_id != scene.id:
            raise not_found("NeRF", nerf_id)
    else:
        nerf = active_nerf(db, scene.id)
        if nerf is None:
            raise not_found("NeRF of scene", scene.name)
    if camera is not None:
        intr = camera
    elif scene.intrinsics is not None:
        intr = Intrinsics.from_dict(scene.intrinsics)
    else:
        raise invalid("intrinsics", "the scene has no camera; give intrinsics")
    if intr.width * intr.height > MAX_RENDER_PIXELS:
        raise invalid(
            "intrinsics", f"{intr.width}x{intr.height} is more than {MAX_RENDER_PIXELS} pixels"
        )
    return RenderTarget(scene.id, NerfFiles(nerf.id, dict(nerf.files)), intr)
