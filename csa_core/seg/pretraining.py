"""Pre-training a segmentation network from scratch on labelled scenes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

from csa_core.data.scene import Scene
from csa_core.errors import CSAInputError
from csa_core.progress import ProgressCallback
from csa_core.seg.checkpoint import ModelCard
from csa_core.seg.config import PretrainConfig
from csa_core.seg.dataset import SegmentationDataset
from csa_core.seg.models import SegmentationNet, build_model
from csa_core.seg.train import TrainResult, seed_everything, train_segmentation
from csa_core.seg.transforms import JointAugment


def pretrain(
    train_scenes: Sequence[Scene],
    config: PretrainConfig | None = None,
    out: str | Path | None = None,
    val_scenes: Sequence[Scene] | None = None,
    weights: str | Path | None = None,
    on_progress: ProgressCallback | None = None,
) -> tuple[SegmentationNet, TrainResult]:
    """Train a fresh network on labelled scenes and keep the best one on the validation views.

    Without ``val_scenes`` the network trains on each scene's training views and is scored
    on each scene's validation views (the split of docs/method.md "Protocols and metrics"). With
    ``val_scenes`` it trains on all views of ``train_scenes`` and is scored on the validation views
    of ``val_scenes``.
    ``weights`` is an optional local safetensors file to start from (torchvision names).
    The checkpoint at ``out`` records the config and the scenes used. ``on_progress`` is
    :func:`~csa_core.seg.train.train_segmentation`'s (per epoch and within long epochs).
    """
    config = config or PretrainConfig()
    if not train_scenes:
        raise CSAInputError("pretrain", "no training scenes")
    for scene in [*train_scenes, *(val_scenes or [])]:
        if scene.size != tuple(config.size):
            raise CSAInputError(
                scene.root or scene.name,
                f"scene is {scene.size[0]}x{scene.size[1]}, the config says "
                f"{config.size[0]}x{config.size[1]}",
            )
    train_split = "all" if val_scenes else "train"
    transform = JointAugment(config.augment) if config.augment is not None else None
    train_set = SegmentationDataset.from_scenes(
        train_scenes, train_split, config.label_folder, transform
    )
    held_out = val_scenes if val_scenes else train_scenes
    val_sets: dict[str, SegmentationDataset] = {}
    for scene in held_out:
        views = SegmentationDataset.from_scenes(scene, "val", config.label_folder)
        key = scene.name
        while key in val_sets:  # two folders of the same name in different places
            key += "'"
        if len(views):
            val_sets[key] = views
    seed_everything(config.train.seed)
    model = build_model(config.arch, weights=weights)
    card = ModelCard.for_model(
        model,
        input_size=list(config.size),
        train_config={
            "task": "pretrain",
            "label_folder": config.label_folder,
            "augment": asdict(config.augment) if config.augment is not None else None,
            "train_scenes": [_scene_ref(s) for s in train_scenes],
            "train_split": train_split,
            "val_scenes": [_scene_ref(s) for s in held_out],
            "train_images": len(train_set),
            "init_weights": str(weights) if weights is not None else None,
        },
    )
    result = train_segmentation(
        model,
        train_set,
        config.train,
        val_sets=val_sets,
        checkpoint=out,
        card=card,
        on_progress=on_progress,
    )
    return model, result


def _scene_ref(scene: Scene) -> str:
    return str(scene.root) if scene.root is not None else scene.name
