"""Replay buffer split and sizes, pre-training slice, batch composition, memory bank."""

from __future__ import annotations

import json

import numpy as np
import pytest

from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.replay import (
    MixedBatchSampler,
    PretrainReplay,
    ReplayBuffer,
    evenly_spaced,
    random_views,
    split_buffer,
)
from csa_core.nerf.fit import fit_semantic_nerf
from tests.nerf.conftest import synthetic_scene, tiny_config


def test_split_buffer_gives_the_remainder_to_the_oldest_scenes():
    assert split_buffer(100, 3) == [34, 33, 33]
    assert split_buffer(100, 4) == [25, 25, 25, 25]
    assert split_buffer(5, 3) == [2, 2, 1]
    assert split_buffer(2, 3) == [1, 1, 0]
    assert split_buffer(100, 0) == []
    assert all(sum(split_buffer(n, k)) == n for n in range(0, 30) for k in range(1, 7))


def test_evenly_spaced_covers_the_trajectory():
    assert evenly_spaced(9, 3) == [0, 4, 8]
    assert evenly_spaced(3, 5) == [0, 1, 2, 0, 1]
    assert evenly_spaced(0, 3) == []


def test_mixed_batches_are_two_current_plus_two_pretraining():
    sampler = MixedBatchSampler(primary=10, secondary=7, seed=3)
    batches = list(sampler)
    assert len(batches) == len(sampler) == 5
    for batch in batches:
        assert len(batch) == 4
        assert sum(i < 10 for i in batch) == 2 and sum(10 <= i < 17 for i in batch) == 2
    primary = sorted(i for b in batches for i in b if i < 10)
    assert primary == list(range(10))  # one epoch = every current/buffer pair once


def test_mixed_batches_without_pretraining_are_all_current():
    batches = list(MixedBatchSampler(primary=9, secondary=0))
    assert [len(b) for b in batches] == [4, 4]  # the lone ninth item is dropped (BatchNorm)
    assert len(set(i for b in batches for i in b)) == 8


def test_pretrain_replay_is_ten_percent_and_seeded(source_scenes_small):
    a = PretrainReplay.from_scenes(source_scenes_small, fraction=0.1, seed=1)
    b = PretrainReplay.from_scenes(source_scenes_small, fraction=0.1, seed=1)
    pool = sum(s.num_train for s in source_scenes_small)
    assert len(a) == round(0.1 * pool) == 2
    assert a.names == b.names
    assert all(
        img.shape[2] == 3 and img.shape[:2] == lab.shape
        for img, lab in zip(a.images, a.labels, strict=True)
    )
    assert len(PretrainReplay.from_scenes(source_scenes_small, fraction=0.0)) == 0


@pytest.fixture(scope="module")
def source_scenes_small():
    return [synthetic_scene(frames=12, size=(32, 24), seed=s) for s in range(2)]


@pytest.fixture(scope="module")
def bank(tmp_path_factory) -> MemoryBank:
    bank = MemoryBank(tmp_path_factory.mktemp("memory"))
    for seed in range(3):
        scene = synthetic_scene(frames=8, size=(32, 24), seed=seed)
        scene.name = f"room {seed}"
        nerf, _ = fit_semantic_nerf(
            scene, "label-nyu40", tiny_config(20), device="cpu", progress=False
        )
        bank.add(scene.name, nerf)
    return bank


def test_memory_bank_stores_one_checkpoint_per_scene(bank):
    assert bank.scenes == ["room 0", "room 1", "room 2"]
    sizes = bank.bytes_per_scene()
    for entry in bank.entries:
        assert (bank.folder / entry.file).stat().st_size == entry.bytes == sizes[entry.scene] > 0
    index = json.loads((bank.folder / "index.json").read_text())
    assert [e["scene"] for e in index["scenes"]] == bank.scenes
    reopened = MemoryBank(bank.folder)
    assert reopened.entries == bank.entries and reopened.total_bytes() == sum(sizes.values())
    nerf = reopened.load("room 1")
    assert nerf.info.name == "room 1" and len(nerf.info.train_frames) == 6


def test_replay_buffer_is_split_equally_at_training_views(bank):
    buffer = ReplayBuffer.from_memory_bank(bank, size=10, views="train")
    assert buffer.per_scene() == {"room 0": 4, "room 1": 3, "room 2": 3}
    assert len(buffer) == 10 and len(set(buffer.names)) == 10
    for img, lab in zip(buffer.images, buffer.labels, strict=True):
        assert img.shape == (24, 32, 3) and img.dtype == np.uint8
        assert lab.shape == (24, 32) and lab.min() >= 1 and lab.max() <= 40
    only = ReplayBuffer.from_memory_bank(bank, size=5, scenes=["room 2"])
    assert only.per_scene() == {"room 2": 5}  # 5 pairs from 6 training views, none repeated
    assert len(set(only.names)) == 5
    assert buffer.nbytes() == 10 * (24 * 32 * 3 + 24 * 32)


def test_replay_buffer_at_novel_views_renders_between_training_frames(bank):
    novel = ReplayBuffer.from_memory_bank(bank, size=6, views="novel")
    train = ReplayBuffer.from_memory_bank(bank, size=6, views="train")
    assert novel.per_scene() == {"room 0": 2, "room 1": 2, "room 2": 2}
    assert all("/novel/" in n and "_" in n.rsplit("/", 1)[1] for n in novel.names)
    assert not any(np.array_equal(a, b) for a, b in zip(novel.images, train.images, strict=True))
    with pytest.raises(ValueError):
        ReplayBuffer.from_memory_bank(bank, size=6, views="val")


def test_paper_split_drops_the_remainder():
    assert split_buffer(100, 3, remainder=False) == [33, 33, 33]
    assert split_buffer(2, 3, remainder=False) == [0, 0, 0]
    assert split_buffer(100, 4, remainder=False) == split_buffer(100, 4)


def test_random_views_are_drawn_without_replacement_then_repeat():
    rng = np.random.default_rng(0)
    picks = random_views(6, 4, rng)
    assert len(set(picks)) == 4 and all(0 <= k < 6 for k in picks)
    many = random_views(6, 14, np.random.default_rng(1))
    assert sorted(many[:6]) == sorted(many[6:12]) == list(range(6)) and len(many) == 14
    assert random_views(0, 3, rng) == [] and random_views(5, 0, rng) == []


def test_replay_buffer_draws_the_papers_random_views(bank):
    """``draw="random"``: floor(size / n) views of every scene at random, seeded; each step
    (number of earlier scenes) draws anew."""
    a = ReplayBuffer.from_memory_bank(bank, size=10, views="train", draw="random", seed=3)
    again = ReplayBuffer.from_memory_bank(bank, size=10, views="train", draw="random", seed=3)
    assert a.per_scene() == {"room 0": 3, "room 1": 3, "room 2": 3}  # 9: no remainder
    assert a.names == again.names  # deterministic
    assert all(np.array_equal(x, y) for x, y in zip(a.images, again.images, strict=True))
    assert len(set(a.names)) == 9
    draws = {
        tuple(ReplayBuffer.from_memory_bank(bank, size=3, draw="random", seed=s).names)
        for s in range(4)
    }
    assert len(draws) > 1  # the seed picks the views
    two = ReplayBuffer.from_memory_bank(
        bank, size=10, scenes=["room 0", "room 1"], draw="random", seed=3
    )
    assert two.per_scene() == {"room 0": 5, "room 1": 5}
    with pytest.raises(ValueError, match="draw"):
        ReplayBuffer.from_memory_bank(bank, size=6, draw="spread")
