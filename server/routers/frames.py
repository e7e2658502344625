"""``/api/v1/scenes/{scene}/frames`` and ``/archive``: upload, list and fetch frames."""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Response, UploadFile, status
from fastapi.responses import FileResponse
from sqlalchemy import Select, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm.exc import StaleDataError
from starlette.concurrency import run_in_threadpool

from csa_core.data.image_files import COLOR_EXTS
from csa_core.data.scene_io import frame_names
from server import faults
from server.archives import ArchiveLimits, UnsafeArchive, extract_archive
from server.auth import DeviceScope, SceneAccess
from server.db.models import Frame, Scene
from server.deps import DbDep, FormPartsChecked, ServicesDep
from server.errors import APIError, invalid, not_found, too_large
from server.frame_store import digest_of, next_frame_name, scene_camera, store_frame
from server.frame_validation import (
    FrameParts,
    NonFinitePose,
    SceneCamera,
    check_frame_name,
    validate_frame,
)
from server.lookups import get_scene
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.quotas import account_of_scene, check_stored_bytes
from server.schemas.common import ERROR_RESPONSES
from server.schemas.frames import ArchiveUploadOut, FrameOut, FrameUploadOut, SkippedFrameOut

# Device keys upload to and read the scenes they created (server/auth.py, check_scene_access).
router = APIRouter(
    prefix="/scenes/{scene_ref}",
    tags=["frames"],
    responses={**ERROR_RESPONSES, 409: ERROR_RESPONSES[422], 413: ERROR_RESPONSES[422]},
    dependencies=[DeviceScope, SceneAccess],
)

_TEXT_LIMIT = 64 * 1024  # pose and intrinsics files are a few hundred bytes


def _race() -> APIError:
    return APIError(409, "conflict", "another upload to this scene ran at the same time; retry")


async def _read(upload: UploadFile | None, field: str, limit: int) -> bytes | None:
    if upload is None:
        return None
    data = await upload.read(limit + 1)
    if len(data) > limit:
        raise too_large(field, limit)
    return data


def _text(data: bytes | None, field: str) -> str | None:
    if data is None:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise invalid(field, "must be UTF-8 text (a whitespace-separated matrix)") from None


def _scene_still_there(db, scene_id: int, scene_ref: str) -> Scene:
    """The scene again after a failed transaction; 404 when a concurrent request deleted it."""
    scene = db.get(Scene, scene_id)
    if scene is None:
        raise not_found("scene", scene_ref)
    return scene


def _frame_name(db, scene: Scene, valid) -> str:
    """The name of a frame uploaded without one: the name its identical content already has
    (uploads are idempotent), else the next number."""
    same = db.scalar(select(Frame).where(Frame.scene_id == scene.id, Frame.content_sha256 == digest_of(valid)).limit(1))
    return same.name if same is not None else next_frame_name(db, scene.id)


def _frame_bytes(valid) -> int:
    """The bytes a frame's files take in the store (the stored-bytes quota, server/quotas.py)."""
    labels = len(valid.labels) if valid.labels is not None else 0
    return len(valid.color) + len(valid.depth) + labels


def _new_bytes(db, scene: Scene, name: str | None, valid) -> int:
    """What storing a frame adds: nothing when the scene holds its content under its name (or
    under any name, for a frame without one), as an identical re-upload."""
    same = (Frame.scene_id == scene.id, Frame.content_sha256 == digest_of(valid))
    query = select(Frame.id).where(*same)
    if name is not None:
        query = query.where(Frame.name == name)
    return 0 if db.scalar(query.limit(1)) is not None else _frame_bytes(valid)


def _store_with_retry(db, services, scene: Scene, name: str | None, valid, replace: bool):
    """Store a frame; a concurrent identical upload that won the race counts as a re-upload,
    a frame without a name that lost the race for the next number takes the one after it, and
    a scene deleted meanwhile is a 404 (its frame row cannot be written)."""
    scene_id, scene_name = scene.id, scene.name
    attempts = 2 if name is not None else 5
    for attempt in range(attempts):
        try:
            outcome = store_frame(db, services.store, scene, name if name is not None else _frame_name(db, scene, valid), valid, replace=replace)
            db.commit()
            return outcome
        except APIError as e:
            if name is not None or e.status != 409:
                raise
            db.rollback()  # the number was taken by a concurrent upload (a frame without a name never conflicts otherwise)
        except (IntegrityError, StaleDataError):  # a concurrent upload, or the scene deleted meanwhile
            db.rollback()
        scene = _scene_still_there(db, scene_id, scene_name)
        if attempt == attempts - 1:
            raise _race() from None
    raise AssertionError("unreachable")


@router.post(
    "/frames",
    response_model=FrameUploadOut,
    status_code=status.HTTP_201_CREATED,
    summary="upload one posed RGB-D frame (idempotent: the same content again changes nothing)",
    dependencies=[FormPartsChecked],
)
async def upload_frame(
    scene_ref: str,
    db: DbDep,
    services: ServicesDep,
    response: Response,
    color: Annotated[UploadFile, File(description="8-bit colour image, PNG or JPEG")],
    depth: Annotated[UploadFile, File(description="depth, single-channel uint16 PNG in millimetres (0 = none)")],
    pose: Annotated[UploadFile, File(description="4x4 camera-to-world matrix as text (metres, OpenCV axes)")],
    intrinsics: Annotated[UploadFile | None, File(description="3x3 or 4x4 colour intrinsics as text; required with a scene's first frame")] = None,
    depth_intrinsics: Annotated[UploadFile | None, File(description="depth camera intrinsics when depth is another camera")] = None,
    labels: Annotated[UploadFile | None, File(description="ground-truth NYU40 label PNG, for evaluation and pre-training only")] = None,
    name: Annotated[str | None, Form(max_length=64, description="frame name (default: the next number)")] = None,
    replace: Annotated[bool, Form(description="overwrite a stored frame of this name that has other content")] = False,
) -> FrameUploadOut:
    scene = get_scene(db, scene_ref)
    limit = services.settings.max_frame_upload_bytes
    parts = FrameParts(
        color=await _read(color, "color", limit) or b"",
        depth=await _read(depth, "depth", limit) or b"",
        pose=_text(await _read(pose, "pose", _TEXT_LIMIT), "pose") or "",
        labels=await _read(labels, "labels", limit),
        intrinsics=_text(await _read(intrinsics, "intrinsics", _TEXT_LIMIT), "intrinsics"),
        depth_intrinsics=_text(await _read(depth_intrinsics, "depth_intrinsics", _TEXT_LIMIT), "depth_intrinsics"),
    )
    if name is not None:
        check_frame_name(name)

    def validate_and_store() -> FrameUploadOut:
        valid = validate_frame(parts, scene_camera(scene), services.settings.max_image_pixels)
        check_stored_bytes(
            db, services.settings, account_of_scene(db, scene), _frame_bytes(valid), "color",
            new_bytes=lambda: _new_bytes(db, scene, name, valid),
        )  # before anything is stored
        outcome = _store_with_retry(db, services, scene, name, valid, replace)
        return FrameUploadOut(**FrameOut.model_validate(outcome.frame).model_dump(), created=outcome.created, replaced=outcome.replaced)

    # Decoding the images, hashing and fsyncing them take a while: in a worker thread, so
    # that the event loop keeps serving every other request meanwhile.
    out = await run_in_threadpool(validate_and_store)
    if not out.created:
        response.status_code = status.HTTP_200_OK
    return out


def frames_query(scene_id: int) -> Select:
    """A scene's frames in order: by order key, then name (unique in a scene, so the order is total)."""
    return select(Frame).where(Frame.scene_id == scene_id).order_by(Frame.order_key, Frame.name)


def all_frames(db, scene_id: int) -> list[FrameOut]:
    """Every frame of a scene, in order: for the dashboard, which pages them itself."""
    return [FrameOut.model_validate(f) for f in db.scalars(frames_query(scene_id))]


@router.get("/frames", response_model=list[FrameOut], responses=PAGE_RESPONSES)
def list_frames(scene_ref: str, db: DbDep, response: Response, pages: PageDep) -> list[FrameOut]:
    """The scene's frames in order (order key, then name), a page at a time; ``X-Total-Count``
    is the number of all its frames."""
    scene = get_scene(db, scene_ref)
    return [FrameOut.model_validate(f) for f in page(db, frames_query(scene.id), pages, response, (Frame.order_key, Frame.name))]


def _get_frame(db, scene: Scene, name: str) -> Frame:
    frame = db.scalar(select(Frame).where(Frame.scene_id == scene.id, Frame.name == name))
    if frame is None:
        raise not_found("frame", name)
    return frame


@router.get("/frames/{name}", response_model=FrameOut)
def show_frame(scene_ref: str, name: str, db: DbDep) -> FrameOut:
    return FrameOut.model_validate(_get_frame(db, get_scene(db, scene_ref), name))


@router.get(
    "/frames/{name}/{part}",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}}, "description": "the stored file"}},
)
def frame_file(scene_ref: str, name: str, part: Literal["color", "depth", "labels"], db: DbDep, services: ServicesDep) -> FileResponse:
    frame = _get_frame(db, get_scene(db, scene_ref), name)
    sha = {"color": frame.color_sha256, "depth": frame.depth_sha256, "labels": frame.labels_sha256}[part]
    if sha is None:
        raise not_found("labels of frame", name)
    ext = frame.color_ext if part == "color" else ".png"
    media = "image/jpeg" if ext == ".jpg" else "image/png"
    return FileResponse(services.store.open_verified(sha), media_type=media, filename=f"{name}{ext}", headers={"ETag": sha})


def _archive_frames(root: Path) -> Path:
    """The scene folder inside an extracted archive: the root itself or its only folder."""
    if (root / "color").is_dir():
        return root
    subdirs = [p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")]
    if len(subdirs) == 1 and (subdirs[0] / "color").is_dir():
        return subdirs[0]
    raise invalid("archive", "no scene folder inside (expected color/, depth/, pose/ and intrinsic/ at the top or in one folder)")


def _color_images(color_dir: Path) -> dict[str, Path]:
    """Frame name -> its colour image in an extracted archive's ``color/`` (the entries
    ``frame_names`` counts: a .jpg/.jpeg/.png suffix in any case, not hidden). A name that is
    not a valid frame name, a name with two images (``0.jpg`` and ``0.png``) or an entry that
    is a folder is refused, naming it."""
    found: dict[str, Path] = {}
    for p in sorted(color_dir.iterdir()):
        if p.suffix.lower() not in COLOR_EXTS or p.name.startswith("."):
            continue
        field = f"archive:color/{p.name}"
        check_frame_name(p.stem, field)  # before frame_names sorts them (digits such as '²' are not numbers)
        if not p.is_file():
            raise invalid(field, "is a folder, not an image file")
        if p.stem in found:
            raise invalid(field, f"frame {p.stem!r} has two colour images ({found[p.stem].name} and {p.name}); keep one")
        found[p.stem] = p
    return found


def _read_member(path: Path, field: str, limit: int) -> bytes:
    if path.exists() and not path.is_file():
        raise invalid(field, "is a folder, not a file")
    if not path.is_file():
        raise invalid(field, "file missing from the archive")
    if path.stat().st_size > limit:
        raise too_large(field, limit)
    return path.read_bytes()


@router.post(
    "/archive",
    response_model=ArchiveUploadOut,
    summary="upload a scene folder as a tar or zip archive (all frames or none)",
    dependencies=[FormPartsChecked],
)
async def upload_archive(
    scene_ref: str,
    db: DbDep,
    services: ServicesDep,
    archive: Annotated[UploadFile, File(description="tar (optionally gz/bz2/xz) or zip of a scene folder")],
    replace: Annotated[bool, Form()] = False,
) -> ArchiveUploadOut:
    scene = get_scene(db, scene_ref)
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
    return await run_in_threadpool(_store_archive, db, services, scene, scene_ref, tmp, replace)


def _archive_new_bytes(db, scene: Scene, valid_frames, sizes: list[int]) -> int:
    """What storing an archive's checked frames adds: the frames whose content the scene does
    not hold under their names yet (read again only when the upload is over the quota)."""
    total = 0
    for (name, checked, (color, depth, labels)), size in zip(valid_frames, sizes, strict=True):
        frame = dataclasses.replace(
            checked,
            color=color.read_bytes(),
            depth=depth.read_bytes(),
            labels=labels.read_bytes() if labels is not None else None,
        )
        if _new_bytes(db, scene, name, frame):
            total += size
    return total


def _store_archive(db, services, scene: Scene, scene_ref: str, tmp: Path, replace: bool) -> ArchiveUploadOut:
    """Extract the archive at ``tmp/upload``, validate its frames and store them all or none;
    removes ``tmp``."""
    st = services.settings
    limits = ArchiveLimits(st.max_archive_members, st.max_archive_member_bytes, st.max_archive_unpacked_bytes, st.max_archive_ratio)
    try:
        packed = tmp / "upload"
        try:
            root = _archive_frames(extract_archive(packed, tmp / "x", limits))
        except UnsafeArchive as e:
            raise invalid("archive", str(e)) from None
        faults.point("archive.extracted")
        packed.unlink()
        color_dir = root / "color"
        colors = _color_images(color_dir)
        names = frame_names(color_dir)
        if not names:
            raise invalid("archive", "color/ holds no .jpg/.png images")
        intr_file = root / "intrinsic" / "intrinsic_color.txt"
        dintr_file = root / "intrinsic" / "intrinsic_depth.txt"
        intr_field, dintr_field = "archive:intrinsic/intrinsic_color.txt", "archive:intrinsic/intrinsic_depth.txt"
        intr_text = _text(_read_member(intr_file, intr_field, _TEXT_LIMIT), intr_field) if scene.intrinsics is None or intr_file.is_file() else None
        dintr_text = _text(_read_member(dintr_file, dintr_field, _TEXT_LIMIT), dintr_field) if dintr_file.exists() else None
        camera = scene_camera(scene)
        valid_frames, skipped = [], []
        limit = st.max_frame_upload_bytes
        for name in names:
            color_path = colors[name]
            labels_path = root / "label-nyu40" / f"{name}.png"
            fields = {
                "color": f"archive:color/{color_path.name}",
                "depth": f"archive:depth/{name}.png",
                "pose": f"archive:pose/{name}.txt",
                "labels": f"archive:label-nyu40/{name}.png",
                "intrinsics": "archive:intrinsic/intrinsic_color.txt",
                "depth_intrinsics": "archive:intrinsic/intrinsic_depth.txt",
            }
            parts = FrameParts(
                color=_read_member(color_path, fields["color"], limit),
                depth=_read_member(root / "depth" / f"{name}.png", fields["depth"], limit),
                pose=_text(_read_member(root / "pose" / f"{name}.txt", fields["pose"], _TEXT_LIMIT), fields["pose"]) or "",
                labels=_read_member(labels_path, fields["labels"], limit) if labels_path.exists() else None,
                intrinsics=intr_text,
                depth_intrinsics=dintr_text,
                fields=fields,
            )
            try:
                valid = validate_frame(parts, camera, st.max_image_pixels)
            except NonFinitePose as e:
                skipped.append(SkippedFrameOut(name=name, reason=e.message))
                continue
            # Later frames of the archive must agree with the first one, as later uploads would.
            camera = SceneCamera(
                intrinsics=camera.intrinsics or valid.intrinsics,
                depth_intrinsics=camera.depth_intrinsics or valid.depth_intrinsics,
                depth_size=camera.depth_size or valid.depth_size,
            )
            # Only the frame's checked facts stay in memory, not its image bytes (up to
            # ``max_archive_unpacked_bytes`` for the whole archive): they are read again from the
            # extracted folder, which nothing else writes, when the frame is stored.
            images = (color_path, root / "depth" / f"{name}.png", labels_path if parts.labels is not None else None)
            valid_frames.append((name, dataclasses.replace(valid, color=b"", depth=b"", labels=None), images))
        if not valid_frames:
            raise invalid("archive", "no frame with a finite pose")
        sizes = [sum(p.stat().st_size for p in files if p is not None) for *_, files in valid_frames]
        check_stored_bytes(
            db, st, account_of_scene(db, scene), sum(sizes), "archive",
            new_bytes=lambda: _archive_new_bytes(db, scene, valid_frames, sizes),
        )  # before anything is stored
        added, unchanged, replaced = [], [], []
        try:
            for name, checked, (color_path, depth_path, labels_path) in valid_frames:
                valid = dataclasses.replace(
                    checked,
                    color=color_path.read_bytes(),
                    depth=depth_path.read_bytes(),
                    labels=labels_path.read_bytes() if labels_path is not None else None,
                )
                outcome = store_frame(db, services.store, scene, name, valid, replace=replace)
                (added if outcome.created else replaced if outcome.replaced else unchanged).append(name)
                faults.point("archive.frame_stored")
            db.commit()
        except (IntegrityError, StaleDataError):  # a concurrent upload, or the scene deleted meanwhile
            db.rollback()
            _scene_still_there(db, scene.id, scene_ref)
            raise _race() from None
        return ArchiveUploadOut(scene_id=scene.id, added=added, unchanged=unchanged, replaced=replaced, skipped=skipped)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
