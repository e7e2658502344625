"""Inputs of jobs, through the core library: scenes read from stored frames, networks from the registry."""

from __future__ import annotations

from pathlib import Path

from csa_core.data import Scene, read_scene
from csa_core.data.camera import parse_size as camera_parse_size
from csa_core.data.scene import NYU40_FOLDER
from server.db.models import ModelVersion
from server.db.models import Scene as SceneRow
from server.jobs.context import JobContext
from server.registry import CHECKPOINT_FILE, checkpoint_sha
from server.scene_folders import write_scene_folder


def parse_size(text: str | None) -> tuple[int, int] | None:
    """A job's optional ``size`` parameter (``WxH``) as (width, height)."""
    return None if text is None else camera_parse_size(text, "size")


def torch_device(ctx: JobContext) -> str | None:
    """The configured device for the core library (None: its own automatic choice)."""
    return None if ctx.settings.device == "auto" else ctx.settings.device


def load_scene(ctx: JobContext, scene_id: int, ground_truth: bool = False, size: tuple[int, int] | None = None) -> Scene:
    """Read a stored scene with the core reader (ground truth as ``label-nyu40`` if asked)."""
    with ctx.session() as s:
        row = s.get(SceneRow, scene_id)
        if row is None:
            raise LookupError(f"scene {scene_id} no longer exists")
        folder = write_scene_folder(s, ctx.store, row, ctx.workdir / "scenes" / f"s{scene_id}", ground_truth=ground_truth)
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
