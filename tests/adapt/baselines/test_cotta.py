"""The CoTTA baseline: stochastic restore, EMA teacher, confidence gate, online steps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from csa_core.adapt.baselines.cotta import CoTTA, CoTTAConfig, module_bytes

C = 40


class ToyNet(nn.Module):
    """A small fully convolutional network with ~156k parameters and 40 output channels."""

    def __init__(self) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(3, 128, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(128, 128, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(128, C, 1),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.body(x)


def num_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@pytest.fixture
def toy() -> ToyNet:
    torch.manual_seed(0)
    return ToyNet()


def image(seed: int = 0, size=(32, 24)) -> np.ndarray:
    w, h = size
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_restore_resets_one_percent_of_elements(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig(seed=3))
    with torch.no_grad():
        for p in cotta.student.parameters():
            p.zero_()  # every element now differs from the (random, non-zero) source
    n = num_params(toy)
    assert n >= 100_000
    restored = cotta.restore()
    equal = sum(
        int((s == src).sum())
        for s, src in zip(cotta.student.parameters(), cotta.source.parameters(), strict=True)
    )
    assert restored == equal
    p = 0.01
    sigma = math.sqrt(n * p * (1 - p))
    assert abs(restored - n * p) < 5 * sigma  # within 1 % +- 0.13 % at n = 156k


def test_restore_extremes_and_seed(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig())
    with torch.no_grad():
        for p in cotta.student.parameters():
            p.add_(1.0)
    snapshot = [p.clone() for p in cotta.student.parameters()]
    assert cotta.restore(0.0) == 0
    assert all(torch.equal(a, b) for a, b in zip(snapshot, cotta.student.parameters(), strict=True))
    masks = []
    for _ in range(2):
        other = CoTTA(ToyNet(), CoTTAConfig(seed=5))
        with torch.no_grad():
            for p in other.student.parameters():
                p.zero_()
        other.restore()
        masks.append([(p != 0).clone() for p in other.student.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*masks, strict=True))
    assert cotta.restore(1.0) == num_params(toy)
    for s, src in zip(cotta.student.parameters(), cotta.source.parameters(), strict=True):
        assert torch.equal(s, src)


def test_teacher_update_is_the_ema_formula(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig(ema_momentum=0.999))
    with torch.no_grad():
        for p in cotta.student.parameters():
            p.copy_(torch.randn_like(p))
    teacher = [p.clone() for p in cotta.teacher.parameters()]
    student = [p.clone() for p in cotta.student.parameters()]
    cotta.update_teacher()
    for t0, s, t1 in zip(teacher, student, cotta.teacher.parameters(), strict=True):
        torch.testing.assert_close(t1, 0.999 * t0 + 0.001 * s)


class PositionTeacher(nn.Module):
    """Logits that depend on the pixel column, so flipping changes the answer.

    Class index 0 scores ``4 * ramp + 1`` (ramp from +1 at the left to -1 at the right),
    class 1 scores 0: at scale 1 the left ~60 % is class 0 and the rest class 1, while the
    average of a plain and a flipped pass prefers class 0 everywhere.
    """

    def forward(self, x: Tensor) -> Tensor:
        b, _, h, w = x.shape
        logits = torch.full((b, C, h, w), -30.0)
        logits[:, 0] = 4.0 * torch.linspace(1.0, -1.0, w) + 1.0
        logits[:, 1] = 0.0
        return logits


class ConfidentTopSource(nn.Module):
    """Confident (class 5, p ~ 1) on the top half, uniform (p = 1/40) on the bottom half;
    records every input it sees."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[Tensor] = []

    def forward(self, x: Tensor) -> Tensor:
        self.seen.append(x.clone())
        b, _, h, w = x.shape
        logits = torch.zeros((b, C, h, w))
        logits[:, 5, : h // 2] = 20.0
        return logits


def test_confidence_gate_uses_the_source_at_scale_one(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig(scales=(1.0,), flip=True))
    cotta.teacher = PositionTeacher()
    source = ConfidentTopSource()
    cotta.source = source
    x = torch.rand(1, 3, 8, 20)
    probs, confident = cotta.pseudo_probabilities(x)
    labels = probs.argmax(1)[0]
    assert len(source.seen) == 1 and torch.equal(source.seen[0], x)  # scale 1, not flipped
    assert confident[0, :4].all() and not confident[0, 4:].any()
    plain = PositionTeacher()(x).argmax(1)[0]
    assert (plain[:, -1] == 1).all() and (plain[:, 0] == 0).all()
    torch.testing.assert_close(labels[:4], plain[:4])  # confident: teacher at scale 1
    assert (labels[4:] == 0).all()  # not confident: the flip average prefers class 0
    assert not torch.equal(labels[4:], plain[4:])


def test_gate_threshold_is_strict(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig(confidence_threshold=1.0))
    cotta.source = ConfidentTopSource()
    _, confident = cotta.pseudo_probabilities(torch.rand(1, 3, 8, 8))
    assert not confident.any()


def test_one_online_step_changes_student_and_teacher(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig(lr=1e-3, scales=(0.5, 1.0), restore_probability=0.01))
    source = [p.clone() for p in cotta.source.parameters()]
    pred = cotta.step(image())
    assert pred.shape == (1, 24, 32) and pred.dtype == np.uint8
    assert pred.min() >= 1 and pred.max() <= 40
    assert cotta.steps == 1 and math.isfinite(cotta.last_loss)
    assert any(
        not torch.equal(a, b) for a, b in zip(source, cotta.student.parameters(), strict=True)
    )
    assert any(
        not torch.equal(a, b) for a, b in zip(source, cotta.teacher.parameters(), strict=True)
    )
    for a, b in zip(source, cotta.source.parameters(), strict=True):
        assert torch.equal(a, b)


def test_cotta_on_a_segmentation_network() -> None:
    from csa_core.seg.models import build_model

    torch.manual_seed(0)
    model = build_model("lraspp_mobilenet_v3_large")
    cotta = CoTTA(model, CoTTAConfig(lr=1e-4, scales=(0.5, 1.0), flip=False))
    preds = cotta.adapt([image(i, (64, 48)) for i in range(2)])
    assert [p.shape for p in preds] == [(48, 64)] * 2
    assert all(1 <= p.min() and p.max() <= 40 for p in preds)
    fp = cotta.footprint()
    assert fp.teacher_bytes == fp.source_bytes == module_bytes(model)
    assert fp.optimizer_bytes == 2 * sum(p.numel() * 4 for p in model.parameters())
    assert fp.extra_copies_bytes == 2 * module_bytes(model)


def test_the_continual_step_trains_the_student_and_reports_the_teacher() -> None:
    """CoTTA as a method of the continual step: the run's network is the student, the
    reported one the teacher, a separate network; both moved, one online step per view."""
    from csa_core.adapt.config import preset
    from csa_core.adapt.methods import ContinualState, CoTTAMethod
    from csa_core.adapt.step import continual_step
    from csa_core.data.synth import generate_scene
    from csa_core.seg.models import build_model

    torch.manual_seed(0)
    model = build_model("lraspp_mobilenet_v3_large")
    before = [p.detach().clone() for p in model.parameters()]
    config = preset("tiny")
    config.seg.device = "cpu"
    scene = generate_scene("office", 0, 4, (32, 24))
    state = ContinualState(CoTTAMethod(config, CoTTAConfig(lr=1e-3, scales=(1.0,), flip=False)))
    record = continual_step(state, model, scene)
    teacher = state.method.reported(model)
    assert teacher is not model and record["online_steps"] == len(scene.train_frames)
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
    assert any(not torch.equal(a, b) for a, b in zip(before, teacher.parameters(), strict=True))


def test_cotta_continues_online_across_scenes(toy: ToyNet) -> None:
    cotta = CoTTA(toy, CoTTAConfig(lr=1e-3, scales=(1.0,), flip=False))
    cotta.adapt([image(0), image(1)])
    teacher_after_first = [p.clone() for p in cotta.teacher.parameters()]
    cotta.adapt([image(2)])  # the next scene: same teacher, student and optimiser
    assert cotta.steps == 3
    assert all(int(s["step"]) == 3 for s in cotta.optimizer.state.values())
    assert any(
        not torch.equal(a, b)
        for a, b in zip(teacher_after_first, cotta.teacher.parameters(), strict=True)
    )


def test_each_preset_sets_the_teachers_scales_and_a_set_overrides_them() -> None:
    """The augmentation CoTTA's teacher averages over lives in the one config tree
    (``AdaptConfig.cotta``): six scales with flips in ``paper`` (docs/method.md "Baselines"),
    three in ``cpu``, one in ``tiny``, and ``--set cotta.scales=...`` reaches the method."""
    from csa_core.adapt.config import preset
    from csa_core.adapt.methods import CoTTAMethod
    from csa_core.errors import CSAInputError
    from csa_core.overrides import apply_overrides

    def settings(config) -> CoTTAConfig:
        return CoTTAMethod(config).cotta_settings

    paper = settings(preset("paper"))
    assert (paper.scales, paper.flip) == ((0.5, 0.75, 1.0, 1.25, 1.5, 1.75), True)
    assert (paper.lr, paper.ema_momentum, paper.confidence_threshold) == (2.5e-6, 0.999, 0.69)
    assert paper.restore_probability == 0.01
    assert settings(preset("cpu")).scales == (0.75, 1.0, 1.5)
    assert settings(preset("tiny")).scales == (1.0,)
    config = apply_overrides(
        preset("cpu"),
        ["cotta.scales=(0.5,0.75,1.0,1.25,1.5,1.75)", "cotta.flip=false", "seg.seed=4"],
    )
    got = settings(config)
    assert (got.scales, got.flip, got.seed) == ((0.5, 0.75, 1.0, 1.25, 1.5, 1.75), False, 4)
    with pytest.raises(CSAInputError, match="scales"):
        apply_overrides(preset("cpu"), ["cotta.scales=(1.0,-0.5)"])
