"""Inputs of jobs, through the core library: scenes read from stored frames, networks from the registry."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from csa_core.data import Scene, read_scene
from csa_core.data.camera import parse_size as camera_parse_size
from csa_core.data.scene import NYU40_FOLDER
from server.db.models import ModelVersion
from server.db.models import Scene as SceneRow
from server.errors import invalid
from server.jobs.context import JobContext
from server.registry import CHECKPOINT_FILE, checkpoint_sha
from server.scene_folders import write_scene_folder


def parse_size(text: str | None) -> tuple[int, int] | None:
    """A job's optional ``size`` parameter (``WxH``) as (width, height)."""
    return None if text is None else camera_parse_size(text, "size")


def check_size(text: str | None, scenes: Sequence[SceneRow], field: str = "params.size") -> tuple[int, int] | None:
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
        raise invalid(field, f"{size[0]}x{size[1]} is larger than the scene's frames ({widest}x{tallest}); jobs work at the frames' size or smaller")
    return size


def torch_device(ctx: JobContext) -> str | None:
    """The configured device for the core library (None: its own automatic choice)."""
    return None if ctx.settings.device == "auto" else ctx.settings.device


def load_scene(ctx: JobContext, scene_id: int, ground_truth: bool = False, size: tuple[int, int] | None = None) -> Scene:
    """Read a stored scene with the core reader (ground truth as ``label-nyu40`` if asked).

    A job may read one scene more than once: an adapt job's target can also be a pre-training
    scene of its lineage, or a scene it scores on. The folder is written on the first read (one
    folder with ground truth, one without) and read again after that: writing it twice would
    link each stored file onto the link already there."""
    dest = ctx.workdir / "scenes" / (f"s{scene_id}-labelled" if ground_truth else f"s{scene_id}")
    with ctx.session() as s:
        row = s.get(SceneRow, scene_id)
        if row is None:
            raise LookupError(f"scene {scene_id} no longer exists")
        folder = dest / row.name
        if not folder.is_dir():
            folder = write_scene_folder(s, ctx.store, row, dest, ground_truth=ground_truth)
    return read_scene(folder, size=size, labels=[NYU40_FOLDER] if ground_truth else [], workers=2)


def model_file(ctx: JobContext, model_id: int) -> tuple[Path, ModelVersion]:
    """The registry's checkpoint file of a version, linked into the job's folder."""
    with ctx.session() as s:
        model = s.get(ModelVersion, model_id)
        if model is None:
            raise LookupError(f"model version {model_id} no longer exists")
        path = ctx.store.materialize(checkpoint_sha(model), ctx.workdir / "models" / str(model_id) / CHECKPOINT_FILE)
    return path, model


def version_file(ctx: JobContext, model_id: int, name: str) -> Path:
    """Another stored file of a version (e.g. its BatchNorm memory), linked into the job's folder."""
    with ctx.session() as s:
        model = s.get(ModelVersion, model_id)
        if model is None:
            raise LookupError(f"model version {model_id} no longer exists")
        sha = (model.files or {}).get(name)
        if sha is None:
            raise LookupError(f"model version {model_id} has no file {name!r}")
        return ctx.store.materialize(sha, ctx.workdir / "models" / str(model_id) / name)
