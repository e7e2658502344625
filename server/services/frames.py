"""Frames: uploads (one frame, or a scene folder as an archive), listing and the stored files
(``/api/v1/scenes/{scene}/frames`` and ``/archive``, the dashboard's scene pages).

Uploads are validated against the scene's camera (``server/frame_validation.py``), counted
against the stored-bytes quota of the scene's owner (``server/quotas.py``) and stored
idempotently (``server/frame_store.py``). The routes read the request's parts; what happens to
them is here.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from sqlalchemy import Select, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from sqlalchemy.orm.exc import StaleDataError

from csa_core.data.image_files import COLOR_EXTS
from csa_core.data.scene_io import frame_names
from server import faults
from server.archives import ArchiveLimits, UnsafeArchive, extract_archive
from server.artifacts import ArtifactStore
from server.db.models import Frame, Scene
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
from server.quotas import account_of_scene, check_stored_bytes
from server.schemas.frames import ArchiveUploadOut, FrameOut, FrameUploadOut, SkippedFrameOut
from server.settings import Settings

TEXT_LIMIT = 64 * 1024  # pose and intrinsics files are a few hundred bytes
# A scene's frames in order: by order key, then name (unique in a scene, so the order is total).
ORDER = (Frame.order_key, Frame.name)


def frames_query(scene_id: int) -> Select:
    """A scene's frames in order (:data:`ORDER`)."""
    return select(Frame).where(Frame.scene_id == scene_id).order_by(*ORDER)


def scene_frames_query(db: Session, scene_ref: str) -> Select:
    """:func:`frames_query` of a scene by id or name; 404 for an unknown scene."""
    return frames_query(get_scene(db, scene_ref).id)


def all_frames(db: Session, scene_id: int) -> list[FrameOut]:
    """Every frame of a scene, in order: for the dashboard, which pages them itself."""
    return [FrameOut.model_validate(f) for f in db.scalars(frames_query(scene_id))]


def names_in_order(db: Session, scene_id: int) -> list[str]:
    """The names of a scene's frames, in order."""
    return list(db.scalars(select(Frame.name).where(Frame.scene_id == scene_id).order_by(*ORDER)))


def depth_files(db: Session, scene_id: int) -> list[str]:
    """The checksums of a scene's depth images, in the frames' order."""
    query = select(Frame.depth_sha256).where(Frame.scene_id == scene_id).order_by(*ORDER)
    return list(db.scalars(query))


def get_frame(db: Session, scene_ref: str | int, name: str) -> Frame:
    """A frame of a scene (by id or name) by its name; 404 for either unknown."""
    scene = get_scene(db, scene_ref)
    frame = db.scalar(select(Frame).where(Frame.scene_id == scene.id, Frame.name == name))
    if frame is None:
        raise not_found("frame", name)
    return frame


def show_frame(db: Session, scene_ref: str, name: str) -> FrameOut:
    return FrameOut.model_validate(get_frame(db, scene_ref, name))


@dataclass(frozen=True)
class FrameFile:
    """One stored file of a frame: its checksum in the artifact store, type and file name."""

    sha256: str
    media_type: str
    filename: str


def frame_file(
    db: Session, scene_ref: str, name: str, part: Literal["color", "depth", "labels"]
) -> FrameFile:
    """The colour image, depth image or labels of a frame; 404 for labels it has none of."""
    frame = get_frame(db, scene_ref, name)
    shas = {"color": frame.color_sha256, "depth": frame.depth_sha256, "labels": frame.labels_sha256}
    sha = shas[part]
    if sha is None:
        raise not_found("labels of frame", name)
    ext = frame.color_ext if part == "color" else ".png"
    media = "image/jpeg" if ext == ".jpg" else "image/png"
    return FrameFile(sha, media, f"{name}{ext}")


# -- uploads -----------------------------------------------------------------------------


def _race() -> APIError:
    return APIError(409, "conflict", "another upload to this scene ran at the same time; retry")


def decode_text(data: bytes | None, field: str) -> str | None:
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
    same = db.scalar(
        select(Frame)
        .where(Frame.scene_id == scene.id, Frame.content_sha256 == digest_of(valid))
        .limit(1)
    )
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


def _store_with_retry(
    db, store: ArtifactStore, scene: Scene, name: str | None, valid, replace: bool
):
    """Store a frame; a concurrent identical upload that won the race counts as a re-upload,
    a frame without a name that lost the race for the next number takes the one after it, and
    a scene deleted meanwhile is a 404 (its frame row cannot be written)."""
    scene_id, scene_name = scene.id, scene.name
    attempts = 2 if name is not None else 5
    for attempt in range(attempts):
        try:
            outcome = store_frame(
                db,
                store,
                scene,
                name if name is not None else _frame_name(db, scene, valid),
                valid,
                replace=replace,
            )
            db.commit()
            return outcome
        except APIError as e:
            if name is not None or e.status != 409:
                raise
            # The number was taken by a concurrent upload (a frame without a name never
            # conflicts otherwise).
            db.rollback()
        except (IntegrityError, StaleDataError):  # a concurrent upload, or the scene deleted
            db.rollback()
        scene = _scene_still_there(db, scene_id, scene_name)
        if attempt == attempts - 1:
            raise _race() from None
    raise AssertionError("unreachable")


def store_uploaded_frame(
    db: Session,
    settings: Settings,
    store: ArtifactStore,
    scene: Scene,
    name: str | None,
    parts: FrameParts,
    replace: bool,
) -> FrameUploadOut:
    """Validate an uploaded frame against the scene's camera, check the stored-bytes quota and
    store it (idempotently: the same content again changes nothing); slow (decoding, hashing,
    fsyncing): callers run it off the event loop."""
    valid = validate_frame(parts, scene_camera(scene), settings.max_image_pixels)
    check_stored_bytes(
        db,
        settings,
        account_of_scene(db, scene),
        _frame_bytes(valid),
        "color",
        new_bytes=lambda: _new_bytes(db, scene, name, valid),
    )  # before anything is stored
    outcome = _store_with_retry(db, store, scene, name, valid, replace)
    return FrameUploadOut(
        **FrameOut.model_validate(outcome.frame).model_dump(),
        created=outcome.created,
        replaced=outcome.replaced,
    )


# -- archives ----------------------------------------------------------------------------


def _archive_frames(root: Path) -> Path:
    """The scene folder inside an extracted archive: the root itself or its only folder."""
    if (root / "color").is_dir():
        return root
    subdirs = [p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")]
    if len(subdirs) == 1 and (subdirs[0] / "color").is_dir():
        return subdirs[0]
    raise invalid(
        "archive",
        "no scene folder inside (expected color/, depth/, pose/ and intrinsic/ at the top or in"
        " one folder)",
    )


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
        # Before frame_names sorts them (digits such as '²' are not numbers).
        check_frame_name(p.stem, field)
        if not p.is_file():
            raise invalid(field, "is a folder, not an image file")
        if p.stem in found:
            two = f"{found[p.stem].name} and {p.name}"
            raise invalid(field, f"frame {p.stem!r} has two colour images ({two}); keep one")
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


def store_archive(
    db: Session,
    settings: Settings,
    store: ArtifactStore,
    scene: Scene,
    scene_ref: str,
    tmp: Path,
    replace: bool,
) -> ArchiveUploadOut:
    """Extract the archive at ``tmp/upload``, validate its frames and store them all or none;
    removes ``tmp``."""
    limits = ArchiveLimits(
        settings.max_archive_members,
        settings.max_archive_member_bytes,
        settings.max_archive_unpacked_bytes,
        settings.max_archive_ratio,
    )
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
        intr_field, dintr_field = (
            "archive:intrinsic/intrinsic_color.txt",
            "archive:intrinsic/intrinsic_depth.txt",
        )
        intr_text = (
            decode_text(_read_member(intr_file, intr_field, TEXT_LIMIT), intr_field)
            if scene.intrinsics is None or intr_file.is_file()
            else None
        )
        dintr_text = (
            decode_text(_read_member(dintr_file, dintr_field, TEXT_LIMIT), dintr_field)
            if dintr_file.exists()
            else None
        )
        camera = scene_camera(scene)
        valid_frames, skipped = [], []
        limit = settings.max_frame_upload_bytes
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
                pose=decode_text(
                    _read_member(root / "pose" / f"{name}.txt", fields["pose"], TEXT_LIMIT),
                    fields["pose"],
                )
                or "",
                labels=_read_member(labels_path, fields["labels"], limit)
                if labels_path.exists()
                else None,
                intrinsics=intr_text,
                depth_intrinsics=dintr_text,
                fields=fields,
            )
            try:
                valid = validate_frame(parts, camera, settings.max_image_pixels)
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
            images = (
                color_path,
                root / "depth" / f"{name}.png",
                labels_path if parts.labels is not None else None,
            )
            valid_frames.append(
                (name, dataclasses.replace(valid, color=b"", depth=b"", labels=None), images)
            )
        if not valid_frames:
            raise invalid("archive", "no frame with a finite pose")
        sizes = [
            sum(p.stat().st_size for p in files if p is not None) for *_, files in valid_frames
        ]
        check_stored_bytes(
            db,
            settings,
            account_of_scene(db, scene),
            sum(sizes),
            "archive",
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
                outcome = store_frame(db, store, scene, name, valid, replace=replace)
                kept = added if outcome.created else replaced if outcome.replaced else unchanged
                kept.append(name)
                faults.point("archive.frame_stored")
            db.commit()
        except (IntegrityError, StaleDataError):  # a concurrent upload, or the scene deleted
            db.rollback()
            _scene_still_there(db, scene.id, scene_ref)
            raise _race() from None
        return ArchiveUploadOut(
            scene_id=scene.id, added=added, unchanged=unchanged, replaced=replaced, skipped=skipped
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
