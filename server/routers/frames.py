"""``/api/v1/scenes/{scene}/frames`` and ``/archive``: upload, list and fetch frames
(``server/services/frames.py``)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Response, UploadFile, status
from fastapi.responses import FileResponse
from starlette.concurrency import run_in_threadpool

from server.auth import DeviceScope, SceneAccess
from server.deps import DbDep, FormPartsChecked, ServicesDep, read_in_thread
from server.errors import too_large
from server.frame_validation import FrameParts, check_frame_name
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.schemas.common import ERROR_RESPONSES, ParamText
from server.schemas.frames import ArchiveUploadOut, FrameOut, FrameUploadOut
from server.services import frames, scenes
from server.services.frames import TEXT_LIMIT, decode_text

# Device keys upload to and read the scenes they created (server/auth.py, check_scene_access).
router = APIRouter(
    prefix="/scenes/{scene_ref}",
    tags=["frames"],
    responses={**ERROR_RESPONSES, 409: ERROR_RESPONSES[422], 413: ERROR_RESPONSES[422]},
    dependencies=[DeviceScope, SceneAccess],
)


async def _read(upload: UploadFile | None, field: str, limit: int) -> bytes | None:
    if upload is None:
        return None
    data = await upload.read(limit + 1)
    if len(data) > limit:
        raise too_large(field, limit)
    return data


@router.post(
    "/frames",
    response_model=FrameUploadOut,
    status_code=status.HTTP_201_CREATED,
    summary="upload one posed RGB-D frame (idempotent: the same content again changes nothing)",
    dependencies=[FormPartsChecked],
)
async def upload_frame(
    scene_ref: ParamText,
    db: DbDep,
    services: ServicesDep,
    response: Response,
    color: Annotated[UploadFile, File(description="8-bit colour image, PNG or JPEG")],
    depth: Annotated[
        UploadFile, File(description="depth, single-channel uint16 PNG in millimetres (0 = none)")
    ],
    pose: Annotated[
        UploadFile, File(description="4x4 camera-to-world matrix as text (metres, OpenCV axes)")
    ],
    intrinsics: Annotated[
        UploadFile | None,
        File(
            description="3x3 or 4x4 colour intrinsics as text; required with a scene's first frame"
        ),
    ] = None,
    depth_intrinsics: Annotated[
        UploadFile | None, File(description="depth camera intrinsics when depth is another camera")
    ] = None,
    labels: Annotated[
        UploadFile | None,
        File(description="ground-truth NYU40 label PNG, for evaluation and pre-training only"),
    ] = None,
    name: Annotated[
        str | None, Form(max_length=64, description="frame name (default: the next number)")
    ] = None,
    replace: Annotated[
        bool, Form(description="overwrite a stored frame of this name that has other content")
    ] = False,
) -> FrameUploadOut:
    scene = await read_in_thread(db, scenes.get_scene, scene_ref)
    limit = services.settings.max_frame_upload_bytes
    parts = FrameParts(
        color=await _read(color, "color", limit) or b"",
        depth=await _read(depth, "depth", limit) or b"",
        pose=decode_text(await _read(pose, "pose", TEXT_LIMIT), "pose") or "",
        labels=await _read(labels, "labels", limit),
        intrinsics=decode_text(await _read(intrinsics, "intrinsics", TEXT_LIMIT), "intrinsics"),
        depth_intrinsics=decode_text(
            await _read(depth_intrinsics, "depth_intrinsics", TEXT_LIMIT), "depth_intrinsics"
        ),
    )
    if name is not None:
        check_frame_name(name)

    # Decoding the images, hashing and fsyncing them take a while: in a worker thread, so
    # that the event loop keeps serving every other request meanwhile.
    out = await run_in_threadpool(
        frames.store_uploaded_frame,
        db,
        services.settings,
        services.store,
        scene,
        name,
        parts,
        replace,
    )
    if not out.created:
        response.status_code = status.HTTP_200_OK
    return out


@router.get("/frames", response_model=list[FrameOut], responses=PAGE_RESPONSES)
def list_frames(
    scene_ref: ParamText, db: DbDep, response: Response, pages: PageDep
) -> list[FrameOut]:
    """The scene's frames in order (order key, then name), a page at a time; ``X-Total-Count``
    is the number of all its frames."""
    rows = page(db, frames.scene_frames_query(db, scene_ref), pages, response, frames.ORDER)
    return [FrameOut.model_validate(f) for f in rows]


@router.get("/frames/{name}", response_model=FrameOut)
def show_frame(scene_ref: ParamText, name: ParamText, db: DbDep) -> FrameOut:
    return frames.show_frame(db, scene_ref, name)


@router.get(
    "/frames/{name}/{part}",
    response_class=FileResponse,
    responses={
        200: {"content": {"image/png": {}, "image/jpeg": {}}, "description": "the stored file"}
    },
)
def frame_file(
    scene_ref: ParamText,
    name: ParamText,
    part: Literal["color", "depth", "labels"],
    db: DbDep,
    services: ServicesDep,
) -> FileResponse:
    file = frames.frame_file(db, scene_ref, name, part)
    return FileResponse(
        services.store.open_verified(file.sha256),
        media_type=file.media_type,
        filename=file.filename,
        headers={"ETag": file.sha256},
    )


@router.post(
    "/archive",
    response_model=ArchiveUploadOut,
    summary="upload a scene folder as a tar or zip archive (all frames or none)",
    dependencies=[FormPartsChecked],
)
async def upload_archive(
    scene_ref: ParamText,
    db: DbDep,
    services: ServicesDep,
    archive: Annotated[
        UploadFile, File(description="tar (optionally gz/bz2/xz) or zip of a scene folder")
    ],
    replace: Annotated[bool, Form()] = False,
) -> ArchiveUploadOut:
    scene = await read_in_thread(db, scenes.get_scene, scene_ref)
    st = services.settings
    tmp = Path(tempfile.mkdtemp(prefix="csa-archive-", dir=services.settings.resolved_work_dir))
    try:
        packed = tmp / "upload"
        size = 0
        with open(packed, "wb") as out:
            while chunk := await archive.read(1 << 20):
                size += len(chunk)
                if size > st.max_archive_bytes:
                    raise too_large("archive", st.max_archive_bytes)
                out.write(chunk)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    # Extracting, validating and storing every frame takes seconds to minutes: in a worker
    # thread (which removes ``tmp``), so that the event loop keeps serving other requests.
    return await run_in_threadpool(
        frames.store_archive,
        db,
        services.settings,
        services.store,
        scene,
        scene_ref,
        tmp,
        replace,
    )
