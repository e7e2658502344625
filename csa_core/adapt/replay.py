"""Replay: a fixed-size buffer rendered from the memory bank, a slice of the pre-training data,
and the batch composition that mixes them with the current scene (docs/method.md "Remember").

Two draws (``ReplayConfig.draw``). ``even`` (ours): ``size`` pairs over ``n`` previous scenes
give every scene ``size // n`` and the first ``size % n`` scenes (the oldest) one more, e.g.
100 over 3 -> 34, 33, 33, and the views are picked evenly spaced along each scene's training
trajectory (or its novel viewpoints, midway between consecutive training frames), so a
scene's share covers the whole room. ``random`` (the paper): every scene gets ``size // n``
(100 over 3 -> 33, 33, 33) views drawn at random without replacement (all of them, in a
random order, repeated when more are asked than there are), from a generator seeded by the
seed and the number of previous scenes, so a run is deterministic and each step draws anew.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.utils.data import Sampler

from csa_core.adapt.memory_bank import NerfMemory
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.nerf.render import render_image, view_poses


def split_buffer(size: int, scenes: int, remainder: bool = True) -> list[int]:
    """Pairs per previous scene: equal shares, the remainder to the oldest scenes (without
    ``remainder``: dropped, the paper's floor(size / scenes) each)."""
    if size < 0 or scenes < 0:
        raise ValueError(f"split_buffer: size and scenes must be >= 0, got {size}, {scenes}")
    if scenes == 0:
        return []
    base, extra = divmod(size, scenes)
    if not remainder:
        extra = 0
    return [base + (1 if k < extra else 0) for k in range(scenes)]


def evenly_spaced(available: int, count: int) -> list[int]:
    """``count`` indices spread evenly over ``range(available)`` (all of them, repeated in
    order, when more are asked than there are)."""
    if available <= 0 or count <= 0:
        return []
    if count >= available:
        return [k % available for k in range(count)]
    return [int(round(x)) for x in np.linspace(0, available - 1, count)]


def random_views(available: int, count: int, rng: np.random.Generator) -> list[int]:
    """``count`` indices of ``range(available)`` drawn at random without replacement (every
    index in a fresh random order, again and again, when more are asked than there are)."""
    if available <= 0 or count <= 0:
        return []
    rounds = -(-count // available)
    return np.concatenate([rng.permutation(available) for _ in range(rounds)])[:count].tolist()


@dataclass
class ReplayBuffer:
    """Image/label pairs rendered from earlier scenes' NeRFs; ``sources[k]`` names the scene of pair
    k."""

    images: list[np.ndarray] = field(default_factory=list)
    labels: list[np.ndarray] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)
    views: str = "train"

    def __len__(self) -> int:
        return len(self.images)

    def per_scene(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for s in self.sources:
            counts[s] = counts.get(s, 0) + 1
        return counts

    def nbytes(self) -> int:
        """Memory held by the buffer's arrays."""
        return int(sum(a.nbytes for a in self.images) + sum(a.nbytes for a in self.labels))

    @classmethod
    def from_memory_bank(
        cls,
        bank: NerfMemory,
        size: int,
        views: str = "train",
        scenes: Sequence[str] | None = None,
        max_render_samples: int | None = None,
        device: str | None = None,
        draw: str = "even",
        seed: int = 0,
    ) -> ReplayBuffer:
        """Render ``size`` pairs split equally among ``scenes`` (default: every scene in the bank)
        at their training or novel viewpoints, the views picked by ``draw`` (``even`` or
        ``random``, seeded by ``seed``; see the module docstring). ``max_render_samples`` caps the
        marching samples per ray: stored NeRFs have no sensor depth to place samples, and on a CPU
        the cap decides what replay costs. The NeRFs render on ``device`` (``None``/``"auto"``:
        CUDA when present), the step's segmentation device."""
        if views not in ("train", "novel"):
            raise ValueError(f"ReplayBuffer: views must be 'train' or 'novel', got {views!r}")
        if draw not in ("even", "random"):
            raise ValueError(f"ReplayBuffer: draw must be 'even' or 'random', got {draw!r}")
        names = list(bank.scenes if scenes is None else scenes)
        buffer = cls(views=views)
        rng = np.random.default_rng([seed, len(names)])
        shares = split_buffer(size, len(names), remainder=draw == "even")
        for scene, count in zip(names, shares, strict=True):
            if count == 0:
                continue
            nerf = bank.load(scene, device=device)
            if max_render_samples is not None:
                nerf.config.sampler.max_render_samples = max_render_samples
            poses = view_poses(nerf, views)
            picked = (
                random_views(len(poses), count, rng)
                if draw == "random"
                else evenly_spaced(len(poses), count)
            )
            for k in picked:
                name, pose = poses[k]
                view = render_image(nerf, pose, name=name)
                buffer.images.append(view.color)
                buffer.labels.append(view.labels)
                buffer.names.append(f"{scene}/{views}/{name}")
                buffer.sources.append(scene)
        return buffer


@dataclass
class PretrainReplay:
    """The slice of the pre-training data that is replayed (camera images and true labels)."""

    images: list[np.ndarray]
    labels: list[np.ndarray]
    names: list[str]

    def __len__(self) -> int:
        return len(self.images)

    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.images) + sum(a.nbytes for a in self.labels))

    @classmethod
    def from_scenes(
        cls,
        scenes: Sequence[Scene],
        fraction: float = 0.1,
        seed: int = 0,
        label_folder: str = NYU40_FOLDER,
        split: str = "train",
    ) -> PretrainReplay:
        """A seeded random ``fraction`` of the pre-training frames (at least one when any exist)."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"PretrainReplay: fraction must be in [0, 1], got {fraction}")
        pool = [(s.name, f) for s in scenes for f in s.split(split) if label_folder in f.labels]
        count = 0 if fraction == 0 or not pool else max(1, int(round(fraction * len(pool))))
        rng = np.random.default_rng(seed)
        chosen = sorted(rng.choice(len(pool), size=count, replace=False).tolist()) if count else []
        return cls(
            images=[pool[k][1].color for k in chosen],
            labels=[pool[k][1].labels[label_folder] for k in chosen],
            names=[f"{pool[k][0]}/{pool[k][1].name}" for k in chosen],
        )


class MixedBatchSampler(Sampler[list[int]]):
    """Batches of ``primary_per_batch`` indices from ``range(primary)`` (current scene and
    replay buffer) plus ``secondary_per_batch`` from ``range(primary, primary + secondary)``
    (pre-training replay), docs/method.md "Remember": 2 + 2.

    One epoch is one shuffled pass over the primary items; the secondary items are drawn
    from their own reshuffled stream. Without secondary items a batch is all primary, of
    size ``primary_per_batch + secondary_per_batch``. A last batch of a single item is dropped
    (BatchNorm needs two).
    """

    def __init__(
        self,
        primary: int,
        secondary: int,
        primary_per_batch: int = 2,
        secondary_per_batch: int = 2,
        seed: int = 0,
    ):
        if primary < 1:
            raise ValueError("MixedBatchSampler: needs at least one primary item")
        self.primary, self.secondary = primary, secondary
        if secondary == 0:
            primary_per_batch, secondary_per_batch = primary_per_batch + secondary_per_batch, 0
        self.p, self.s = primary_per_batch, secondary_per_batch
        self.generator = torch.Generator().manual_seed(seed)
        self._stream: list[int] = []

    def _next_secondary(self) -> int:
        if not self._stream:
            self._stream = (
                self.primary + torch.randperm(self.secondary, generator=self.generator)
            ).tolist()
        return self._stream.pop()

    def __len__(self) -> int:
        full, rest = divmod(self.primary, self.p)
        return full + (1 if rest and rest + self.s >= 2 else 0)

    def __iter__(self) -> Iterator[list[int]]:
        order = torch.randperm(self.primary, generator=self.generator).tolist()
        for start in range(0, self.primary, self.p):
            batch = order[start : start + self.p] + [self._next_secondary() for _ in range(self.s)]
            if len(batch) >= 2:
                yield batch
