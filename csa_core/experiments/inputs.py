"""What every experiment reads: a pre-trained network, the scene sequence, seeds and a preset.

Inputs are checked before any work starts, so a wrong path or a scene without ground truth
fails in a second with one line naming it, not after an hour of NeRF fits. Each run gets a
fresh copy of the pre-trained network and a config whose seeds are all the run's seed, so
runs are independent and repeatable.
"""

from __future__ import annotations

import copy
import json
import platform
import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from csa_core.adapt.config import MODES, AdaptConfig, preset
from csa_core.adapt.methods import check_method
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.overrides import apply_overrides
from csa_core.seg.checkpoint import ModelCard
from csa_core.seg.models import SegmentationNet

# ``--adabn`` of the experiments: every method with AdaBN, without, or both runs side by side.
ADABN_CHOICES: tuple[str, ...] = ("on", "off", "both")


def seeded(config: AdaptConfig, seed: int) -> AdaptConfig:
    """A copy of ``config`` with every seed (NeRF, fine-tuning, replay) set to ``seed``."""
    config = copy.deepcopy(config)
    config.nerf.seed = config.seg.seed = config.replay.seed = int(seed)
    return config


def parse_seeds(text: str) -> list[int]:
    """``"0,1,2"`` -> ``[0, 1, 2]``; an input error for anything else or repeated seeds."""
    try:
        seeds = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise CSAInputError("--seeds", f"expected integers like 0,1,2, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise CSAInputError("--seeds", f"expected distinct integers like 0,1,2, got {text!r}")
    return seeds


def load_scenes(
    paths: Sequence[Path], size: tuple[int, int] | None, need_ground_truth: bool
) -> list[Scene]:
    """Read scene folders at ``size``; with ``need_ground_truth`` every frame must have
    ``label-nyu40`` (the experiments score against it) and names must be unique."""
    from csa_core.data.scene_io import read_scene

    scenes = []
    for path in paths:
        scene = read_scene(path, size=size)
        if need_ground_truth and any(NYU40_FOLDER not in f.labels for f in scene.frames):
            raise CSAInputError(
                Path(path) / NYU40_FOLDER,
                "ground truth needed to score this scene (every frame needs a label-nyu40 map)",
            )
        scenes.append(scene)
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise CSAInputError("scenes", f"scene folder names must be unique, got {names}")
    return scenes


def versions() -> dict[str, str]:
    """Versions of what produced a result (recorded in every config.json)."""
    import numpy
    import torchvision

    from csa_core import __version__

    return {
        "csa": __version__,
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "torchvision": torchvision.__version__,
        "numpy": numpy.__version__,
        "platform": platform.platform(),
        "torch_threads": str(torch.get_num_threads()),
    }


@dataclass
class ExperimentInputs:
    """The pre-trained network and the data of an experiment, and how runs are configured."""

    model_path: Path
    model: SegmentationNet
    card: ModelCard
    scenes: list[Scene]
    scene_paths: list[Path]
    out: Path
    preset: str = "cpu"
    seeds: list[int] = field(default_factory=lambda: [0])
    pretrain_scenes: list[Scene] = field(default_factory=list)
    pretrain_paths: list[Path] = field(default_factory=list)
    size: tuple[int, int] | None = None
    device: str | None = None
    mode: str | None = None  # ours' mode in the continual protocol (None: the preset's)
    methods: list[str] | None = None  # None: the experiment's default list
    adabn: str | None = None  # "on", "off" or "both" (None: the preset's AdaptConfig.adabn)
    # ``--set KEY=VALUE`` items, applied to every run's config after everything else
    overrides: list[str] = field(default_factory=list)
    # Reuse runs an earlier invocation finished (``--resume``): see :meth:`finished_run`.
    resume: bool = False

    def network(self) -> SegmentationNet:
        """A fresh copy of the pre-trained network (runs must not share weights)."""
        return copy.deepcopy(self.model)

    def run_folder(self, *parts: str) -> Path:
        """An empty folder ``out/runs/<parts>`` for one run. A folder left by an earlier
        invocation is removed first: a stale NeRF memory bank there would be replayed."""
        folder = self.out.joinpath("runs", *parts)
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        return folder

    def finished_run(
        self,
        parts: Sequence[str],
        config: AdaptConfig,
        method: str,
        b: np.ndarray,
        scenes: Sequence[Scene] | None = None,
    ):
        """With :attr:`resume`, the ``ContinualResult`` an earlier invocation wrote to
        ``out/runs/<parts>/results.json``, if that run finished (its metrics are written
        last) with the same scenes (``scenes``, default the inputs' sequence: a one-step run
        is a run over its one scene), pre-training scenes, method and config, and the same
        pre-trained network (``b``, the network's validation mIoU per scene, must match
        exactly); else ``None`` and the run is done again."""
        from csa_core.adapt.continual import ContinualResult

        if not self.resume:
            return None
        path = self.out.joinpath("runs", *parts, "results.json")
        try:
            stored = json.loads(path.read_text())
            result = ContinualResult.from_dict(stored)
        except (OSError, ValueError, KeyError, TypeError):
            return None
        recorded = dict(result.config)
        expected = json.loads(json.dumps(config.to_dict(), default=float))
        defaults = json.loads(json.dumps(AdaptConfig().to_dict(), default=float))
        same = (
            bool(result.metrics)
            and result.scenes == [s.name for s in (self.scenes if scenes is None else scenes)]
            and recorded.pop("method", None) == method
            and recorded.pop("pretrain_scenes", None) == [s.name for s in self.pretrain_scenes]
            and _same_config(expected, recorded, defaults)
            and result.b.shape == b.shape
            and np.array_equal(result.b, b)
        )
        return result if same else None

    def config(self, seed: int, mode: str | None = None, adabn: bool | None = None) -> AdaptConfig:
        """The preset's config with every seed set to ``seed``, ``mode`` (or the inputs'
        mode), ``adabn`` (``None``: the preset's) and the device, then the ``overrides``
        (the last word: ``--set nerf.seed=3`` fixes that seed for every run)."""
        config = seeded(preset(self.preset), seed)
        config.mode = mode or self.mode or config.mode
        if adabn is not None:
            config.adabn = adabn
        config.seg.device = self.device
        return apply_overrides(config, self.overrides)

    def adabn_variants(self) -> list[bool]:
        """The AdaBN settings to run each method with: ``[True, False]`` for ``both``,
        one of them for ``on`` / ``off``, the preset's own otherwise; a ``--set adabn=...``
        override replaces the one setting (with ``both`` it is refused by
        :func:`load_inputs`)."""
        if self.adabn == "both":
            return [True, False]
        flag = None if self.adabn is None else self.adabn == "on"
        return [self.config(self.seeds[0], adabn=flag).adabn]

    def describe(self) -> dict[str, Any]:
        """The inputs as recorded in config.json."""
        return {
            "model": str(self.model_path),
            "model_card": {
                "arch": self.card.arch,
                "weights_id": self.card.weights_id,
                "input_size": self.card.input_size,
            },
            "scenes": [str(p) for p in self.scene_paths],
            "scene_names": [s.name for s in self.scenes],
            "pretrain_scenes": [str(p) for p in self.pretrain_paths],
            "preset": self.preset,
            "mode": self.mode,
            "methods": self.methods,
            "adabn": self.adabn,
            "overrides": self.overrides,
            "seeds": self.seeds,
            "size": list(self.size) if self.size else None,
            "device": self.device,
        }


def _same_config(expected: Any, recorded: Any, defaults: Any) -> bool:
    """Whether a recorded config (JSON) is ``expected``: equal field by field, where a field
    the record lacks (added to the code since) counts as equal if ``expected`` has it at its
    default; fields only the record has (removed since) are ignored."""
    if isinstance(expected, dict):
        if not isinstance(recorded, dict):
            return False
        defaults = defaults if isinstance(defaults, dict) else {}
        for key, value in expected.items():
            if key in recorded:
                if not _same_config(value, recorded[key], defaults.get(key)):
                    return False
            elif key not in defaults or defaults[key] != value:
                return False
        return True
    return expected == recorded


def check_options(
    preset_name: str,
    mode: str | None = None,
    adabn: str | None = None,
    overrides: Sequence[str] = (),
) -> list[str]:
    """Check the preset, mode, AdaBN choice and ``--set`` items (on the preset) before any
    work; returns the overrides as a list."""
    from csa_core.adapt.config import PRESETS

    if preset_name not in PRESETS:
        raise CSAInputError(
            "--preset", f"unknown preset {preset_name!r} (choose from {', '.join(PRESETS)})"
        )
    if mode is not None and mode not in MODES:
        raise CSAInputError("--mode", f"unknown mode {mode!r} (choose from {', '.join(MODES)})")
    if adabn is not None and adabn not in ADABN_CHOICES:
        raise CSAInputError("--adabn", f"expected one of {', '.join(ADABN_CHOICES)}, got {adabn!r}")
    overrides = list(overrides)
    apply_overrides(preset(preset_name), overrides)
    if adabn == "both" and any(item.partition("=")[0].strip() == "adabn" for item in overrides):
        raise CSAInputError(
            "--set adabn", "--adabn both runs every method with and without AdaBN: drop one of them"
        )
    return overrides


def load_inputs(
    model_path: Path,
    scene_paths: Sequence[Path],
    out: Path,
    preset_name: str = "cpu",
    seeds: Sequence[int] = (0,),
    pretrain_paths: Sequence[Path] = (),
    size: tuple[int, int] | None = None,
    device: str | None = None,
    mode: str | None = None,
    methods: Sequence[str] | None = None,
    allowed_methods: Sequence[str] = (),
    need_ground_truth: bool = True,
    adabn: str | None = None,
    overrides: Sequence[str] = (),
    resume: bool = False,
) -> ExperimentInputs:
    """Check and load everything an experiment needs. ``size`` defaults to the size the
    network was trained at (then the scenes' own); ``methods`` must be in ``allowed_methods``;
    ``overrides`` (``--set`` items) are checked on the preset before anything is loaded."""
    from csa_core.device import resolve_device
    from csa_core.seg.checkpoint import load_checkpoint

    overrides = check_options(preset_name, mode, adabn, overrides)
    for name in methods or ():
        check_method(name, allowed_methods, "--methods")
    if methods is not None and not methods:
        raise CSAInputError("--methods", "no method given")
    if not scene_paths:
        raise CSAInputError("--scenes", "no scene folders given")
    model, card = load_checkpoint(model_path, device=resolve_device(device))
    if size is None and card.input_size:
        size = (int(card.input_size[0]), int(card.input_size[1]))
    scenes = load_scenes(scene_paths, size, need_ground_truth)
    pretrain = load_scenes(pretrain_paths, size, need_ground_truth=True) if pretrain_paths else []
    return ExperimentInputs(
        model_path=Path(model_path),
        model=model,
        card=card,
        scenes=scenes,
        scene_paths=[Path(p) for p in scene_paths],
        out=Path(out),
        preset=preset_name,
        seeds=list(seeds),
        pretrain_scenes=pretrain,
        pretrain_paths=[Path(p) for p in pretrain_paths],
        size=size,
        device=device,
        mode=mode,
        methods=list(methods) if methods is not None else None,
        adabn=adabn,
        overrides=overrides,
        resume=resume,
    )
