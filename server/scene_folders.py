"""Stored scenes as scene folders (the data contract's layout), for the core library to read.

Jobs never read the database's blobs directly: a job's ``gather`` names a scene's frames and
their files (``server.jobs.inputs.SceneInput``), and its ``compute`` builds a scene folder of
hard links to those files and reads it with :func:`csa_core.data.read_scene`, so the service
accepts exactly what the command line accepts.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from csa_core.data import image_files
from csa_core.data.camera import Intrinsics
from csa_core.data.scene import NYU40_FOLDER
from csa_core.errors import CSAInputError
from server.db.models import Frame, Scene
from server.jobs.phases import link

if TYPE_CHECKING:
    from server.jobs.inputs import SceneInput


def _write_intrinsics(path: Path, intr: Intrinsics) -> None:
    K = np.eye(4)
    K[:3, :3] = intr.matrix()
    image_files.write_matrix(path, K)


def labels_problem(frames: int, unlabelled: int, example: str | None) -> str | None:
    """Why a scene of ``frames`` frames, ``unlabelled`` of them without ground truth (the
    first one named ``example``), cannot be read with ground truth; None when it can."""
    if not frames:
        return "has no frames yet"
    if unlabelled:
        return (
            f"{unlabelled} of {frames} frames have no ground-truth labels (e.g. {example}); "
            "this job needs labels on every frame"
        )
    return None


def missing_ground_truth(session: Session, scene: Scene) -> str | None:
    """Why ``scene`` cannot be read with ground truth (no frames, or frames without labels), or
    None: the rule of :func:`write_scene_folder`, checked early by the jobs' ``prepare``."""
    n, labelled = session.execute(
        select(func.count(Frame.id), func.count(Frame.labels_sha256)).where(
            Frame.scene_id == scene.id
        )
    ).one()
    example = None
    if n and labelled < n:
        example = session.scalar(
            select(Frame.name)
            .where(Frame.scene_id == scene.id, Frame.labels_sha256.is_(None))
            .order_by(Frame.order_key, Frame.name)
            .limit(1)
        )
    return labels_problem(n, n - labelled, example)


def write_scene_folder(scene: SceneInput, dest: Path, ground_truth: bool = False) -> Path:
    """Write ``scene`` as a scene folder at ``dest`` (a new folder named after the scene).

    ``ground_truth`` adds the uploaded labels as ``label-nyu40``; they are for evaluation and
    pre-training only, so adaptation and NeRF fitting on predictions never see them.
    """
    frames = scene.frames
    if not frames or scene.intrinsics is None:
        raise CSAInputError(f"scene {scene.name}", "has no frames yet")
    if ground_truth:
        unlabelled = [f.name for f in frames if f.labels is None]
        example = unlabelled[0] if unlabelled else None
        problem = labels_problem(len(frames), len(unlabelled), example)
        if problem is not None:
            raise CSAInputError(f"scene {scene.name}", problem)
    root = dest / scene.name
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    color_cam = Intrinsics.from_dict(scene.intrinsics)
    _write_intrinsics(root / "intrinsic" / "intrinsic_color.txt", color_cam)
    if scene.depth_intrinsics:
        _write_intrinsics(
            root / "intrinsic" / "intrinsic_depth.txt", Intrinsics.from_dict(scene.depth_intrinsics)
        )
    for f in frames:
        link(f.color, root / "color" / f"{f.name}{f.color_ext}")
        link(f.depth, root / "depth" / f"{f.name}.png")
        image_files.write_matrix(
            root / "pose" / f"{f.name}.txt", np.asarray(f.pose, dtype=np.float64)
        )
        if ground_truth and f.labels is not None:
            link(f.labels, root / NYU40_FOLDER / f"{f.name}.png")
    return root
