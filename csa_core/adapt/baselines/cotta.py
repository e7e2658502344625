"""The CoTTA baseline (Wang et al., CVPR 2022): continual test-time adaptation, online.

One pass over the target images, one image per step. A teacher (exponential moving average of
the student) labels each image, averaging its softmax over flips and scales, except at pixels
where the frozen source network is already confident at scale 1: there the teacher's plain
scale-1 prediction is used. The student takes one Adam step of cross-entropy on those
pseudo-labels, the teacher follows, and each trainable weight element is reset to its source
value with a small probability (stochastic restore), which keeps long runs from drifting.

Choices of ours, for CNNs with BatchNorm at batch size 1: BatchNorm layers keep the source
running statistics (their affine weights still adapt), because batch statistics of one image
break layers that see a 1x1 map (DeepLabv3's image pooling). Pseudo-labels are hard (arg-max),
as in CoTTA's segmentation experiments; ``soft_labels`` switches to the teacher's probabilities.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from csa_core.adapt.config import CPU_COTTA_SCALES, PAPER_COTTA_SCALES
from csa_core.data.scene import Frame
from csa_core.device import resolve_device
from csa_core.seg.predict import as_image_list
from csa_core.seg.transforms import image_to_tensor, to_float_image

# docs/method.md "Baselines" (CoTTA): lr 2.5e-6, EMA 0.999, confidence gate 0.69, restore p = 0.01.
PAPER_LR = 2.5e-6
PAPER_EMA_MOMENTUM = 0.999
PAPER_CONFIDENCE_THRESHOLD = 0.69
PAPER_RESTORE_PROBABILITY = 0.01


@dataclass(frozen=True)
class CoTTAConfig:
    """CoTTA's settings; defaults are the paper's (docs/method.md, "Baselines")."""

    lr: float = PAPER_LR
    betas: tuple[float, float] = (0.9, 0.999)  # Adam's defaults, as in CoTTA
    ema_momentum: float = PAPER_EMA_MOMENTUM
    confidence_threshold: float = PAPER_CONFIDENCE_THRESHOLD
    restore_probability: float = PAPER_RESTORE_PROBABILITY
    scales: tuple[float, ...] = PAPER_COTTA_SCALES
    flip: bool = True
    soft_labels: bool = False
    seed: int = 0
    device: str | None = None

    def __post_init__(self) -> None:
        if not self.lr > 0:
            raise ValueError(f"CoTTAConfig: lr must be > 0, got {self.lr}")
        for name in ("ema_momentum", "confidence_threshold", "restore_probability"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"CoTTAConfig: {name} must be in [0, 1], got {v}")
        if not self.scales or any(s <= 0 for s in self.scales):
            raise ValueError(f"CoTTAConfig: scales must be positive, got {self.scales}")

    @classmethod
    def cpu(cls, **overrides: object) -> CoTTAConfig:
        """The paper's constants with fewer augmentation scales, for CPU runs."""
        return cls(**{"scales": CPU_COTTA_SCALES, **overrides})  # type: ignore[arg-type]


def module_bytes(model: nn.Module) -> int:
    """Bytes of a network's parameters and buffers (what one more copy of it costs)."""
    tensors = {id(t): t for t in [*model.parameters(), *model.buffers()]}
    return sum(t.numel() * t.element_size() for t in tensors.values())


@dataclass(frozen=True)
class CoTTAFootprint:
    """Memory CoTTA adds to the network itself: teacher and source copies, Adam's moments."""

    teacher_bytes: int
    source_bytes: int
    optimizer_bytes: int

    @property
    def extra_copies_bytes(self) -> int:
        """The two extra network copies (the footprint the method comparison counts)."""
        return self.teacher_bytes + self.source_bytes

    @property
    def total_bytes(self) -> int:
        return self.extra_copies_bytes + self.optimizer_bytes


ImageInput = np.ndarray | Sequence[np.ndarray] | Tensor


class CoTTA:
    """Online CoTTA around a segmentation network (``images -> (B, C, H, W) logits``).

    ``student`` is the given network, adapted in place; ``teacher`` and ``source`` are copies
    made at construction. Channel ``k`` of the logits is NYU40 id ``k + 1``.
    """

    def __init__(self, model: nn.Module, config: CoTTAConfig | None = None):
        self.config = config or CoTTAConfig()
        self.device = resolve_device(self.config.device)
        self.student = model.to(self.device)
        self.teacher = copy.deepcopy(model).eval()
        self.source = copy.deepcopy(model).eval()
        for net in (self.teacher, self.source):
            net.requires_grad_(False)
        self.optimizer = torch.optim.Adam(
            [p for p in self.student.parameters() if p.requires_grad],
            lr=self.config.lr,
            betas=self.config.betas,
        )
        self.generator = torch.Generator(device=self.device).manual_seed(self.config.seed)
        self.steps = 0
        self.last_loss = float("nan")
        self.last_confident_fraction = float("nan")

    def _as_batch(self, images: ImageInput) -> Tensor:
        if isinstance(images, Tensor):
            x = to_float_image(images)
            if x.ndim == 3:
                x = x[None]
        else:
            batch, _ = as_image_list(images)
            x = to_float_image(torch.stack([image_to_tensor(img) for img in batch]))
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"CoTTA: expected (B, 3, H, W) images, got {tuple(x.shape)}")
        return x.to(self.device)

    @torch.no_grad()
    def teacher_probabilities(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Teacher softmax at scale 1, and averaged over the configured scales and flips."""
        h, w = x.shape[-2:]
        plain = F.softmax(self.teacher(x), dim=1)
        total = torch.zeros_like(plain)
        count = 0
        for scale in self.config.scales:
            size = (max(1, round(h * scale)), max(1, round(w * scale)))
            xs = (
                x
                if size == (h, w)
                else F.interpolate(x, size=size, mode="bilinear", align_corners=False)
            )
            for flip in (False, True) if self.config.flip else (False,):
                if size == (h, w) and not flip:
                    total += plain
                else:
                    logits = self.teacher(xs.flip(-1) if flip else xs)
                    if flip:
                        logits = logits.flip(-1)
                    if logits.shape[-2:] != (h, w):
                        logits = F.interpolate(
                            logits, size=(h, w), mode="bilinear", align_corners=False
                        )
                    total += F.softmax(logits, dim=1)
                count += 1
        return plain, total / count

    @torch.no_grad()
    def source_confidence(self, x: Tensor) -> Tensor:
        """(B, H, W) largest softmax probability of the frozen source network at scale 1."""
        return F.softmax(self.source(x), dim=1).amax(dim=1)

    @torch.no_grad()
    def pseudo_probabilities(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Teacher probabilities per pixel after the gate: the plain scale-1 prediction where
        the source is confident (> threshold), the augmentation average elsewhere; and the
        (B, H, W) mask of confident pixels."""
        plain, averaged = self.teacher_probabilities(x)
        confident = self.source_confidence(x) > self.config.confidence_threshold
        return torch.where(confident[:, None], plain, averaged), confident

    def step(self, images: ImageInput) -> np.ndarray:
        """One online step on a batch (CoTTA uses one image): returns the teacher's gated
        predictions as (B, H, W) uint8 NYU40 ids, computed before this step's update."""
        x = self._as_batch(images)
        probs, confident = self.pseudo_probabilities(x)
        self.student.eval()  # source BatchNorm statistics; see the module notes
        logits = self.student(x)
        if self.config.soft_labels:
            loss = -(probs * F.log_softmax(logits, dim=1)).sum(dim=1).mean()
        else:
            loss = F.cross_entropy(logits, probs.argmax(dim=1))
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.update_teacher()
        self.restore()
        self.steps += 1
        self.last_loss = float(loss.detach())
        self.last_confident_fraction = float(confident.float().mean())
        return (probs.argmax(dim=1) + 1).to(torch.uint8).cpu().numpy()

    @torch.no_grad()
    def update_teacher(self) -> None:
        """teacher <- m * teacher + (1 - m) * student, parameter by parameter."""
        m = self.config.ema_momentum
        for t, s in zip(self.teacher.parameters(), self.student.parameters(), strict=True):
            t.mul_(m).add_(s.detach(), alpha=1.0 - m)

    @torch.no_grad()
    def restore(self, probability: float | None = None) -> int:
        """Reset each trainable weight element of the student to its source value with
        ``probability`` (default: the config's), drawing from the seeded generator.
        Returns how many elements were reset."""
        p = self.config.restore_probability if probability is None else probability
        restored = 0
        if p <= 0:
            return 0
        for s, src in zip(self.student.parameters(), self.source.parameters(), strict=True):
            if not s.requires_grad:
                continue
            mask = torch.rand(s.shape, generator=self.generator, device=s.device) < p
            s.copy_(torch.where(mask, src, s))
            restored += int(mask.sum())
        return restored

    def adapt(self, images: Iterable[np.ndarray | Frame]) -> list[np.ndarray]:
        """One online pass, one image per step; returns each image's (H, W) prediction."""
        out = []
        for item in images:
            image = item.color if isinstance(item, Frame) else item
            out.append(self.step(image)[0])
        return out

    def footprint(self) -> CoTTAFootprint:
        """Bytes of the teacher and source copies and of Adam's two moment buffers."""
        moments = sum(
            t.numel() * t.element_size()
            for state in self.optimizer.state.values()
            for t in state.values()
            if isinstance(t, Tensor) and t.ndim > 0
        )
        if not moments:  # before the first step Adam has not allocated them yet
            moments = 2 * sum(
                p.numel() * p.element_size() for p in self.student.parameters() if p.requires_grad
            )
        return CoTTAFootprint(module_bytes(self.teacher), module_bytes(self.source), moments)
