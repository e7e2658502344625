"""``paper`` is the paper's configuration (docs/presets.md "The paper preset"): every number it
fixes, read from the objects the adaptation step builds, and the joint schedule and the NeRF budgets
counted in a real run of a scaled-down copy on a tiny room."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from torch import nn

import csa_core.adapt.finetune as finetune
from csa_core.adapt.config import AdaptConfig, paper
from csa_core.adapt.finetune import SegFinetuner, step_nerf_budget, training_pairs
from csa_core.adapt.methods import pretrain_context
from csa_core.adapt.modes import adapt_one_step
from csa_core.adapt.nerf_training import NerfLabelTrainer
from csa_core.adapt.pseudo_labels import nerf_config
from csa_core.data.scene import Scene
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.hash_encoding import level_resolutions
from csa_core.nerf.normalization import fixed_cube_box, scene_box_from_frames
from csa_core.nerf.trainer import NerfTrainer
from csa_core.seg.train import SegmentationTrainer

SMALL = (16, 16)


def small_room(frames: int = 6, seed: int = 10) -> Scene:
    """A tiny office without ground truth (so a run scores and renders nothing extra)."""
    from csa_core.data.synth import generate_scene

    scene = generate_scene("office", seed, frames, SMALL)
    for f in scene.frames:
        f.labels = {}
    return scene


def with_mode(config: AdaptConfig, mode: str) -> AdaptConfig:
    config = copy.deepcopy(config)
    config.mode = mode
    config.seg.device = "cpu"
    return config


def test_the_nerf_is_the_papers():
    scene = small_room(frames=10)
    views = len(scene.train_frames)
    budgets = {"gi_nl": 60, "ni_nl": 60, "joint": 10}  # NeRF epochs before the pseudo-labels
    configs = {m: nerf_config(step_nerf_budget(with_mode(paper(), m), scene)) for m in budgets}
    for mode, epochs in budgets.items():
        assert configs[mode].optim.steps == epochs * views  # one 4096-ray batch per view
    cfg = configs["joint"]
    assert cfg.preset == "reference"
    enc = cfg.field.encoding
    assert (enc.num_levels, enc.features_per_level) == (16, 2)
    assert (enc.log2_table_size, enc.base_resolution, enc.finest_resolution) == (19, 16, 8192)
    # The official per-level scale, exp2(log2(2048 * bound / 16) / 15) with bound 4:
    resolutions = level_resolutions(enc)
    official = 2 ** (math.log2(2048 * 4 / 16) / 15)
    assert resolutions[0] == 16 and resolutions[1] == math.floor(16 * official)
    s = cfg.sampler
    assert (s.train, s.render, s.render_depth_guided) == ("reference", "reference", False)
    assert (s.uniform_samples, s.importance_samples) == (256, 256)
    o = cfg.optim
    assert (o.rays_per_step, o.lr, o.betas, o.eps) == (4096, 1e-2, (0.9, 0.99), 1e-15)
    assert o.final_lr_fraction == 1.0  # a fixed rate
    assert o.ray_batches == "per_view"  # each step's rays from one image, as the official code
    assert o.semantics_in_fit and o.semantic_steps == 0
    f = cfg.field
    assert (f.hidden_dim, f.density_hidden_layers, f.geo_features) == (64, 1, 15)
    assert (f.color_hidden_layers, f.semantic_hidden_layers, f.sh_degree) == (2, 1, 4)
    assert f.semantic_grid_levels == 0  # no semantic feature table (ours)
    assert f.semantic_detach_geometry is True  # the paper's stop-gradient before geometry
    # The official code's fixed cube: the grid spans [-4, 4]^3 of a scene scaled so that the
    # cameras average 1.32 units from the point they look at.
    assert (cfg.normalization, cfg.cube_bound, cfg.cube_camera_distance) == ("cube", 4.0, 1.32)
    loss = cfg.loss
    assert (loss.color, loss.depth, loss.semantic, loss.free_space) == (1.0, 0.1, 0.04, 0.0)
    assert (cfg.storage_dtype, cfg.appearance) == ("float32", "none")

    # The model and the optimiser built from it.
    nerf, _ = fit_semantic_nerf(scene, None, cfg, device="cpu", steps=0, progress=False)
    assert (
        nerf.box
        == fixed_cube_box(scene.train_frames, 4.0, 1.32)
        != scene_box_from_frames(scene.train_frames, scene.intrinsics)
    )
    assert nerf.field.semantic_table is None
    linear = [m for m in nerf.field.semantic_mlp if isinstance(m, nn.Linear)]
    assert [m.in_features for m in linear] == [15, 64]  # geometry features, one hidden layer
    encoding = nerf.field.encoding
    assert len(encoding.level_sizes) == 16 and max(encoding.level_sizes) == 2**19
    assert encoding.level_sizes[-12:] == [2**19] * 12  # levels finer than 80^3 are hashed
    assert encoding.table.shape == (sum(encoding.level_sizes), 2)
    assert encoding.resolutions[-1] == pytest.approx(8192, abs=1)
    trainer = NerfLabelTrainer(nerf, scene).trainer
    assert trainer.rays_per_step == 4096
    groups = trainer.optimizer.param_groups
    assert {(g["lr"], g["betas"], g["eps"]) for g in groups} == {(1e-2, (0.9, 0.99), 1e-15)}
    assert trainer.scheduler.gamma == 1.0
    frames = {int(i) // trainer.rays.hw for i in trainer.draw()[0]}
    assert len(frames) == 1  # one view per step


def test_the_network_and_its_training_are_the_papers(pretrained):
    from csa_core.cli.main import build_parser
    from csa_core.cli.seg import pretrain_config
    from csa_core.seg.models import build_model

    config = paper()
    assert (config.seg.lr, config.seg.batch_size, config.seg.epochs) == (1e-5, 4, 50)
    assert config.seg.schedule == "constant"
    # The official augmentation: jitter 0.3/0.3/0.3/0.05, rotation 10 degrees, flip 0.5, and
    # a crop of the image scaled by 1.2.
    a = config.seg.augment
    assert (a.brightness, a.contrast, a.saturation, a.hue) == (0.3, 0.3, 0.3, 0.05)
    assert (a.rotation_deg, a.hflip, a.crop_aspect_jitter) == (10.0, 0.5, 0.0)
    assert a.crop_scale == pytest.approx((1 / 1.44, 1 / 1.44))
    assert tuner_dataset_augment(config) == a  # what the training pairs are augmented with
    tuner = SegFinetuner(copy.deepcopy(pretrained), with_mode(config, "joint"), 50, 10)
    assert [g["lr"] for g in tuner.trainer.optimizer.param_groups] == [1e-5]
    assert isinstance(tuner.trainer.optimizer, torch.optim.Adam)
    # Replay: 100 pairs, 10% of the pre-training data, batches of 2 current-or-buffer + 2
    # pre-training images, as the sampler the training loop uses draws them.
    assert (config.replay.buffer_size, config.replay.pretrain_fraction) == (100, 0.1)
    assert (config.replay.views, config.replay.draw) == ("train", "random")
    batches = list(tuner.batches(primary=7, secondary=20))
    assert [sum(i >= 7 for i in b) for b in batches] == [2, 2, 2, 2]
    assert [sum(i < 7 for i in b) for b in batches] == [2, 2, 2, 1]  # one pass over the 7
    # The network: DeepLabv3-ResNet101 at 320x240, through `csa seg pretrain --preset paper`.
    args = build_parser().parse_args(["seg", "pretrain", "x", "--out", "y", "--preset", "paper"])
    pre = pretrain_config(args)
    assert (pre.arch, pre.size) == ("deeplabv3_resnet101", (320, 240))
    assert (pre.train.lr, pre.train.batch_size, pre.train.epochs) == (1e-4, 4, 150)
    # The rate decays linearly from 1e-4 to 1e-6, as the trainer's scheduler runs it.
    assert (pre.train.schedule, pre.train.final_lr) == ("linear", 1e-6)
    trainer = SegmentationTrainer(nn.Conv2d(3, 2, 1), pre.train, total_steps=10)
    rates = []
    for _ in range(11):
        rates.append(trainer.lr)
        trainer.optimizer.step()
        trainer.scheduler.step()
    expected = [1e-4 - (1e-4 - 1e-6) * k / 10 for k in range(11)]
    assert rates == pytest.approx(expected, rel=1e-9)
    official = build_parser().parse_args(
        ["seg", "pretrain", "x", "--out", "y", "--preset", "paper", "--schedule", "poly"]
    )
    assert pretrain_config(official).train.final_lr == 1e-6  # the official config's decay
    net = build_model(pre.arch)  # torchvision, weights=None: nothing downloaded
    blocks = [len(getattr(net.net.backbone, f"layer{k}")) for k in range(1, 5)]
    assert blocks == [3, 4, 23, 3]  # ResNet-101
    assert net.net.classifier[-1].out_channels == 40
    # No collapse guard, AdaBN where the paper uses it, no BatchNorm memory.
    assert not config.collapse.enabled and not config.pool_batchnorm
    assert config.adabn and config.adabn_placement == "paper"
    assert (config.mode, config.joint.schedule, config.joint.epochs) == ("joint", "batch", 50)


def tuner_dataset_augment(config):
    """The augmentation the adaptation's training pairs get under ``config``."""
    images = [np.zeros((8, 8, 3), np.uint8)]
    labels = [np.ones((8, 8), np.int64)]
    dataset, _, _ = training_pairs(images, labels, augment=config.seg.augment)
    return dataset.transform.config


class Recorder:
    """Counts what a run does, in order: NeRF steps (with their loss terms), network steps
    (with their batch size) and AdaBN passes."""

    def __init__(self, monkeypatch):
        self.events: list[str] = []
        self.nerf_terms: list[set[str]] = []
        nerf_step, seg_step = NerfTrainer.step, SegmentationTrainer.step
        adabn = finetune.adapt_batchnorm

        def on_nerf(trainer, *a, **k):
            terms = nerf_step(trainer, *a, **k)
            self.events.append("nerf")
            self.nerf_terms.append(set(terms))
            return terms

        def on_seg(trainer, images, labels):
            self.events.append(f"seg{len(images)}")
            return seg_step(trainer, images, labels)

        def on_adabn(*a, **k):
            self.events.append("adabn")
            return adabn(*a, **k)

        monkeypatch.setattr(NerfTrainer, "step", on_nerf)
        monkeypatch.setattr(SegmentationTrainer, "step", on_seg)
        monkeypatch.setattr(finetune, "adapt_batchnorm", on_adabn)

    def clear(self) -> None:
        self.events.clear()
        self.nerf_terms.clear()


def scaled_paper(mode: str) -> AdaptConfig:
    """``paper`` with its budgets scaled down for a test: NeRF epochs 10 + 50 -> 1 + 2 and
    60 -> 3, network epochs 50 -> 2, a small grid and ray batch. Everything else (samplers,
    optimisers, schedule, replay, guard, AdaBN) is the paper's."""
    config = with_mode(paper(), mode)
    config.nerf.joint_prefit_epochs, config.nerf.prefit_epochs = 1, 3
    config.joint.rounds = config.seg.epochs = 2
    config.nerf.add_overrides(
        [
            "optim.rays_per_step=32",
            "field.encoding.log2_table_size=10",
            "field.encoding.num_levels=4",
            "field.encoding.finest_resolution=64",
        ]
    )
    return config


def test_joint_training_alternates_per_batch_with_the_fine_tuning_budget(pretrained, monkeypatch):
    from csa_core.data.synth import generate_scene

    scene = small_room()
    source_scenes = [generate_scene("apartment", k, 5, SMALL) for k in range(2)]  # labelled
    views = len(scene.train_frames)
    recorder = Recorder(monkeypatch)
    runs = {}
    for mode in ("joint", "gi_nl"):
        config = scaled_paper(mode)
        pretrain, _ = pretrain_context(source_scenes, config)
        recorder.clear()
        result = adapt_one_step(
            copy.deepcopy(pretrained), scene, config, pretrain=pretrain, evaluate_before=False
        )
        runs[mode] = (list(recorder.events), list(recorder.nerf_terms), result)

    # Fine-tuning: the NeRF fits 3 epochs (one ray batch per view each), then the network
    # trains 2 epochs; no AdaBN (GI+NL trains on camera images).
    events, terms, result = runs["gi_nl"]
    fit = events.count("nerf")
    assert fit == 3 * views == result.nerf_steps["fit"]
    assert events[:fit] == ["nerf"] * fit and "nerf" not in events[fit:]
    assert "adabn" not in events
    batches = sum(e.startswith("seg") for e in events)

    # Joint: 1 pre-fit epoch, then every network batch is preceded by one full NeRF step per
    # current-scene view in it (2 of the batch's 4 images; the other 2 are pre-training).
    events, terms, result = runs["joint"]
    prefit = views
    assert events[:prefit] == ["nerf"] * prefit and result.nerf_steps["fit"] == prefit
    joint = events[prefit:]
    assert joint[-1] == "adabn" and joint.count("adabn") == 1  # once, after rendered images
    runs_of_nerf = []
    count = 0
    for e in joint[:-1]:
        if e == "nerf":
            count += 1
        else:
            assert e == f"seg{count + 2}"  # the batch: its current views + 2 pre-training images
            runs_of_nerf.append(count)
            count = 0
    assert count == 0  # the last event before AdaBN is a network step
    per_epoch = len(runs_of_nerf) // 2
    assert len(runs_of_nerf) == 2 * per_epoch == batches  # same network batches as GI+NL
    for epoch in (runs_of_nerf[:per_epoch], runs_of_nerf[per_epoch:]):
        assert sum(epoch) == views and all(1 <= k <= 2 for k in epoch)
    assert result.nerf_steps["joint"] == 2 * views
    # The NeRF keeps its colour, depth and semantic losses in every joint step ...
    assert all({"color", "depth", "semantic"} <= t for t in terms[prefit:])
    # ... and the budgets are equal: 1 + 2 epochs = 3 epochs.
    assert events.count("nerf") == runs["gi_nl"][0].count("nerf")
    assert [h["nerf_steps"] for h in result.history] == [views, views]
    assert all(np.isfinite(h["loss"]) for h in result.history)


@pytest.mark.parametrize("mode", ["ni_nl", "joint", "gi_nl"])
def test_adabn_runs_only_after_training_on_rendered_images(mode):
    config = with_mode(paper(), mode)
    assert not config.adabn_before_labels
    assert config.adabn_after_training(rendered=mode != "gi_nl") is (mode != "gi_nl")
    assert config.adabn_after_training(rendered=False) is False
    ours = with_mode(paper(), mode)
    ours.adabn_placement = "ours"
    assert ours.adabn_before_labels and ours.adabn_after_training(rendered=False)


def test_adabn_skips_every_method_that_trains_on_camera_images(monkeypatch):
    """The paper uses AdaBN only for networks trained on rendered images: under ``paper``
    Mapping, CoTTA and fine-tuning end their steps without it; placed ``ours`` they get it
    before labelling and at the end of the step."""
    import csa_core.adapt.methods as methods

    calls = []
    monkeypatch.setattr(methods, "apply_adabn", lambda *a, **k: calls.append(a[0]))
    scene = small_room()
    for name in ("mapping", "cotta", "finetune"):
        for placement, expected in (("paper", 0), ("ours", 2)):
            config = with_mode(paper(), "joint")
            config.adabn_placement = placement
            method = methods.make_method(name, config)
            calls.clear()
            method._adabn(nn.BatchNorm2d(3), scene, None, before_labels=True)
            method._adabn(nn.BatchNorm2d(3), scene, None)
            assert len(calls) == expected, (name, placement)


def test_paper_official_takes_the_official_code_side():
    from csa_core.adapt.config import paper_official, preset

    official, ours = paper_official(), paper()
    assert preset("paper-official") == official and official.preset == "paper-official"
    # The semantic loss reaches geometry: one item after paper's own.
    assert nerf_config(official.nerf).field.semantic_detach_geometry is False
    assert official.nerf.overrides == (*ours.nerf.overrides, "field.semantic_detach_geometry=false")
    assert official.adabn is False  # the official code has no AdaBN step
    official.preset, official.adabn = ours.preset, ours.adabn
    official.nerf.overrides = ours.nerf.overrides
    assert official == ours  # nothing else differs
