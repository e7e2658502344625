"""Inputs of jobs: scenes and model versions as plain values, read by ``gather`` and turned
back into the core library's objects by ``compute`` (``server/jobs/phases.py``).

:func:`gather_scene` and :func:`gather_model` read a scene's frames and a version's files on
the API node; :func:`load_scene` and :func:`model_file` build scene folders and checkpoint
files from them in the job's folder, with no database.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from csa_core.data import Scene, read_scene
from csa_core.data.camera import parse_size as camera_parse_size
from csa_core.data.scene import NYU40_FOLDER
from server.artifacts import ArtifactStore
from server.db.models import Frame, ModelVersion
from server.db.models import Scene as SceneRow
from server.errors import invalid
from server.jobs.context import JobContext
from server.jobs.phases import FileRef, link, stored_file
from server.registry import CHECKPOINT_FILE
from server.scene_folders import write_scene_folder


def parse_size(text: str | None) -> tuple[int, int] | None:
    """A job's optional ``size`` parameter (``WxH``) as (width, height)."""
    return None if text is None else camera_parse_size(text, "size")


def check_size(
    text: str | None, scenes: Sequence[SceneRow], field: str = "params.size"
) -> tuple[int, int] | None:
    """A job's optional working size, refused (422 naming ``field``) when it is larger than the
    colour frames of all its ``scenes``: a job holds every frame at this size, so upsampling
    would only multiply its memory (a 40x30 scene read at 8192x8192 takes gigabytes), while the
    frames themselves are bounded by the upload limits."""
    size = parse_size(text)
    if size is None:
        return None
    widest = max((int(s.intrinsics["width"]) for s in scenes if s.intrinsics), default=0)
    tallest = max((int(s.intrinsics["height"]) for s in scenes if s.intrinsics), default=0)
    if size[0] > widest or size[1] > tallest:
        raise invalid(
            field,
            f"{size[0]}x{size[1]} is larger than the scene's frames ({widest}x{tallest}); jobs "
            "work at the frames' size or smaller",
        )
    return size


def torch_device(ctx: JobContext) -> str | None:
    """The configured device for the core library (None: its own automatic choice)."""
    return None if ctx.settings.device == "auto" else ctx.settings.device


# -- scenes --------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameInput:
    """One stored frame: its name, pose and files (``labels``: the uploaded ground truth)."""

    name: str
    color_ext: str
    pose: list[Any]  # 4x4 camera-to-world, row-major, as stored
    color: FileRef
    depth: FileRef
    labels: FileRef | None


@dataclass(frozen=True)
class SceneInput:
    """A stored scene: its cameras and frames in order."""

    id: int
    name: str
    intrinsics: dict[str, Any] | None
    depth_intrinsics: dict[str, Any] | None
    frames: list[FrameInput]

    @property
    def labelled(self) -> bool:
        """Whether every frame has ground truth."""
        return bool(self.frames) and all(f.labels is not None for f in self.frames)


def gather_scene(session: Session, store: ArtifactStore, scene_id: int) -> SceneInput:
    """A stored scene with its frames and their files (ground truth included where uploaded;
    :func:`load_scene` adds it to the folder only when asked)."""
    row = session.get(SceneRow, scene_id)
    if row is None:
        raise LookupError(f"scene {scene_id} no longer exists")
    frames = session.scalars(
        select(Frame).where(Frame.scene_id == scene_id).order_by(Frame.order_key, Frame.name)
    ).all()
    return SceneInput(
        id=row.id,
        name=row.name,
        intrinsics=row.intrinsics,
        depth_intrinsics=row.depth_intrinsics,
        frames=[
            FrameInput(
                name=f.name,
                color_ext=f.color_ext,
                pose=f.pose,
                color=stored_file(store, f.color_sha256),
                depth=stored_file(store, f.depth_sha256),
                labels=stored_file(store, f.labels_sha256) if f.labels_sha256 else None,
            )
            for f in frames
        ],
    )


def load_scene(
    scene: SceneInput,
    workdir: Path,
    ground_truth: bool = False,
    size: tuple[int, int] | None = None,
) -> Scene:
    """Read a gathered scene with the core reader (ground truth as ``label-nyu40`` if asked).

    A job may read one scene more than once: an adapt job's target can also be a pre-training
    scene of its lineage, or a scene it scores on. The folder is written on the first read (one
    folder with ground truth, one without) and read again after that: writing it twice would
    link each stored file onto the link already there."""
    dest = workdir / "scenes" / (f"s{scene.id}-labelled" if ground_truth else f"s{scene.id}")
    folder = dest / scene.name
    if not folder.is_dir():
        folder = write_scene_folder(scene, dest, ground_truth=ground_truth)
    return read_scene(folder, size=size, labels=[NYU40_FOLDER] if ground_truth else [], workers=2)


# -- model versions ------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelInput:
    """A model version: its name and architecture and the files a job reads (file name ->
    file: the checkpoint, and e.g. the BatchNorm memory)."""

    id: int
    name: str
    arch: str
    files: dict[str, FileRef]


def gather_model(
    session: Session, store: ArtifactStore, model_id: int, files: Sequence[str] = (CHECKPOINT_FILE,)
) -> ModelInput:
    """A model version with those of its ``files`` it has."""
    model = session.get(ModelVersion, model_id)
    if model is None:
        raise LookupError(f"model version {model_id} no longer exists")
    have = model.files or {}
    return ModelInput(
        model.id,
        model.name,
        model.arch,
        {name: stored_file(store, have[name]) for name in files if name in have},
    )


def model_file(model: ModelInput, workdir: Path, name: str = CHECKPOINT_FILE) -> Path:
    """A file of a version (the checkpoint by default), linked into the job's folder."""
    ref = model.files.get(name)
    if ref is None:
        raise LookupError(f"model version {model.id} has no file {name!r}")
    return link(ref, workdir / "models" / str(model.id) / name)
