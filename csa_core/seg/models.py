"""Segmentation networks: torchvision architectures with 40 NYU40 outputs, built without downloads.

Output channel ``k`` scores NYU40 id ``k + 1``; id 0 (unknown) has no channel, so a network
always names a real class. Networks take RGB images as floats in [0, 1] and normalise them
themselves, so the normalisation travels with the checkpoint instead of living in every caller.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn
from torchvision.models import segmentation as tvseg

from csa_core.data.nyu40 import NUM_CLASSES
from csa_core.errors import CSAInputError
from csa_core.seg.config import DEFAULT_ARCH
from csa_core.seg.safetensors_io import read_safetensors

# ImageNet statistics: what torchvision's backbones expect, so a user's local ImageNet or COCO
# weights see the inputs they were trained on.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class ArchSpec:
    """One buildable architecture: its torchvision builder and a line for listings."""

    name: str
    builder: Callable[..., nn.Module]
    description: str


ARCHS: dict[str, ArchSpec] = {
    spec.name: spec
    for spec in (
        ArchSpec(
            "deeplabv3_resnet101",
            tvseg.deeplabv3_resnet101,
            "the paper's network (59 M parameters); GPU-sized",
        ),
        ArchSpec(
            "deeplabv3_resnet50",
            tvseg.deeplabv3_resnet50,
            "DeepLabv3 on ResNet-50 (40 M parameters)",
        ),
        ArchSpec(
            "deeplabv3_mobilenet_v3_large",
            tvseg.deeplabv3_mobilenet_v3_large,
            "DeepLabv3 head on MobileNetV3-Large (11 M parameters)",
        ),
        ArchSpec(
            "lraspp_mobilenet_v3_large",
            tvseg.lraspp_mobilenet_v3_large,
            "LR-ASPP on MobileNetV3-Large (3.2 M parameters); the CPU default",
        ),
    )
}


class SegmentationNet(nn.Module):
    """A torchvision segmentation model behind a plain ``images -> logits`` interface.

    ``forward`` takes (B, 3, H, W) RGB floats in [0, 1] and returns (B, num_classes, H, W)
    logits; channel ``k`` is NYU40 id ``k + 1``. The input normalisation is held in
    non-persistent buffers: it is metadata, recorded beside the weights in checkpoints.
    """

    def __init__(
        self,
        arch: str,
        net: nn.Module,
        num_classes: int,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
    ):
        super().__init__()
        self.arch = arch
        self.num_classes = num_classes
        self.net = net
        self.register_buffer(
            "mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1), persistent=False
        )

    @property
    def normalization(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(mean, std) per RGB channel applied to [0, 1] inputs."""
        return tuple(self.mean.flatten().tolist()), tuple(self.std.flatten().tolist())

    def forward(self, images: Tensor) -> Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(
                f"SegmentationNet: expected (B, 3, H, W) images, got {tuple(images.shape)}"
            )
        return self.net((images - self.mean) / self.std)["out"]


def build_model(
    arch: str = DEFAULT_ARCH,
    num_classes: int = NUM_CLASSES,
    mean: Sequence[float] = IMAGENET_MEAN,
    std: Sequence[float] = IMAGENET_STD,
    weights: str | Path | None = None,
) -> SegmentationNet:
    """Build ``arch`` with freshly initialised weights (never downloaded).

    ``weights`` optionally names a local safetensors file of torchvision-named tensors (for
    example a converted ImageNet backbone or COCO model); tensors whose name and shape match
    are copied, see :func:`load_foreign_weights`. To resume from a CSA checkpoint use
    :func:`csa_core.seg.checkpoint.load_checkpoint` instead.
    """
    spec = ARCHS.get(arch)
    if spec is None:
        raise ValueError(f"unknown architecture {arch!r} (known: {', '.join(ARCHS)})")
    if num_classes < 1:
        raise ValueError(f"num_classes must be >= 1, got {num_classes}")
    net = spec.builder(weights=None, weights_backbone=None, num_classes=num_classes, aux_loss=False)
    model = SegmentationNet(arch, net, num_classes, mean, std)
    if weights is not None:
        load_foreign_weights(model, weights)
    return model


def load_foreign_weights(model: SegmentationNet, path: str | Path) -> tuple[list[str], list[str]]:
    """Copy matching tensors from a local safetensors file of torchvision names into ``model``.

    Names are tried as they are, under ``backbone.`` (a bare backbone such as ResNet or
    MobileNetV3's ``features.*``, whose classifier is dropped by the match) and with a
    leading ``net.`` of our own wrapper. Tensors of another shape (e.g. a 21-class COCO head)
    are skipped. Returns (loaded, skipped) names of the file; loads nothing and raises
    :class:`CSAInputError` when no tensor matches, so a wrong file never passes silently.
    """
    tensors, _ = read_safetensors(path)
    target = model.net.state_dict()
    updates: dict[str, Tensor] = {}
    skipped: list[str] = []
    for name, tensor in tensors.items():
        key = _match_key(name, target)
        if key is not None and target[key].shape == tensor.shape:
            updates[key] = tensor
        else:
            skipped.append(name)
    if not updates:
        raise CSAInputError(
            path,
            f"no tensor matches {model.arch} by name and shape ({len(tensors)} tensors in the "
            "file)",
        )
    model.net.load_state_dict(updates, strict=False)
    return [n for n in tensors if n not in skipped], skipped


def _match_key(name: str, target: dict[str, Tensor]) -> str | None:
    candidates = [name, f"backbone.{name}"]
    if name.startswith("net."):
        candidates.append(name[len("net.") :])
    if name.startswith("features."):
        candidates.append(f"backbone.{name[len('features.') :]}")
    return next((c for c in candidates if c in target), None)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
