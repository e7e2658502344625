"""Scene folders and a checkpoint on disk for the experiment and ``csa adapt`` commands.

Two office rooms of 8 frames at 48x36 (the sequence, with ground truth), one apartment room
(pre-training replay), a copy of the first office without labels, and a light network
pre-trained for two epochs on two apartment rooms: not good, but not constant either, so
adaptation, fusion and the guard have something to work on. Everything is seeded.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import pytest

from csa_core.cli.main import main

SIZE = (48, 36)
FRAMES = 8


@dataclass(frozen=True)
class Workspace:
    model: Path
    scenes: list[Path]
    pretrain: Path
    unlabelled: Path


@pytest.fixture(scope="session")
def workspace(tmp_path_factory) -> Workspace:
    import torch

    from csa_core.data.scene_io import write_scene
    from csa_core.data.synth import generate_scene
    from csa_core.seg.checkpoint import ModelCard, save_checkpoint
    from csa_core.seg.config import PretrainConfig, TrainConfig
    from csa_core.seg.pretraining import pretrain

    root = tmp_path_factory.mktemp("experiment-inputs")
    offices = [generate_scene("office", 10 + k, FRAMES, SIZE, name=f"office_{k}") for k in range(2)]
    scenes = [write_scene(s, root / "scenes" / s.name) for s in offices]
    source = [generate_scene("apartment", k, FRAMES, SIZE) for k in range(2)]
    pre = write_scene(source[0], root / "pretrain" / source[0].name)
    bare = copy.deepcopy(offices[0])
    for f in bare.frames:
        f.labels = {}
    unlabelled = write_scene(bare, root / "unlabelled" / "office_0")
    torch.manual_seed(0)
    config = PretrainConfig(
        size=SIZE,
        train=TrainConfig(
            epochs=2, batch_size=4, progress=False, precise_bn_images=16, device="cpu"
        ),
    )
    model, _ = pretrain(source, config)
    ckpt = root / "model.safetensors"
    save_checkpoint(ckpt, model, ModelCard.for_model(model, input_size=list(SIZE)))
    return Workspace(model=ckpt, scenes=scenes, pretrain=pre, unlabelled=unlabelled)


def csa(capsys, *argv: object) -> tuple[int, str, str]:
    """Run ``csa`` in-process; returns (exit code, stdout, stderr)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err
