"""Settings of segmentation training, kept free of torch so command lines can show them cheaply.

Pre-training values are ours, sized for a light network on a 2-core CPU; the paper's values
(docs/method.md "Reference numbers") are named as such.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from csa_core.data.scene import NYU40_FOLDER

# Architectures csa_core.seg.models can build (torchvision names).
ARCH_NAMES = (
    "deeplabv3_resnet101",
    "deeplabv3_resnet50",
    "deeplabv3_mobilenet_v3_large",
    "lraspp_mobilenet_v3_large",
)
# docs/method.md "Reference numbers": DeepLabv3-ResNet101, 40 NYU classes.
PAPER_ARCH = "deeplabv3_resnet101"
DEFAULT_ARCH = "lraspp_mobilenet_v3_large"  # ours: 3.2 M parameters, trains on a CPU

# docs/method.md "Reference numbers": images 320x240 (width x height).
PAPER_SIZE = (320, 240)
# The paper's pre-training (docs/presets.md "Pre-training presets"): Adam lr decayed linearly
# from 1e-4 to 1e-6 (the official config decays it polynomially, power 0.9, to 1e-6) over 150
# epochs, batch 4; flips, rotations of up to 10 degrees, crops of the image scaled by 1.2 and
# colour jitter 0.3 / 0.3 / 0.3 / 0.05.
PAPER_PRETRAIN_LR = 1e-4
PAPER_PRETRAIN_FINAL_LR = 1e-6
PAPER_PRETRAIN_EPOCHS = 150
PAPER_PRETRAIN_BATCH_SIZE = 4

SCHEDULES = ("poly", "linear", "cosine", "constant")


@dataclass
class TrainConfig:
    """Optimiser, schedule and loop settings.

    The defaults are ours, for pre-training a light network from scratch on a CPU; the
    paper's adaptation values are in :class:`csa_core.adapt.config.SegBudget`. ``lr`` is Adam's
    initial rate, decayed per step to ``final_lr`` (0 unless set) by ``schedule`` (``poly``:
    (1 - t)^poly_power, ``linear``, ``cosine``; ``constant`` keeps ``lr``). Every ``val_every``
    epochs (and after the last) the model is scored. Before each validation the BatchNorm running
    statistics are recomputed on up to
    ``precise_bn_images`` training images (0 disables): in a run of a few hundred steps the
    running averages lag far behind the weights (MobileNetV3's momentum is 0.01), and a
    network scored with stale statistics looks much worse than it is.
    """

    epochs: int = 12
    batch_size: int = 8
    lr: float = 2e-3
    schedule: str = "poly"
    poly_power: float = 0.9
    final_lr: float = 0.0  # where a decaying schedule ends (the paper's pre-training: 1e-6)
    weight_decay: float = 0.0
    precise_bn_images: int = 128
    seed: int = 0
    val_every: int = 1
    device: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if self.schedule not in SCHEDULES:
            raise ValueError(
                f"TrainConfig: schedule must be one of {SCHEDULES}, got {self.schedule!r}"
            )
        if self.epochs < 1 or self.batch_size < 1 or self.val_every < 1:
            raise ValueError("TrainConfig: epochs, batch_size and val_every must be >= 1")
        if not self.lr > 0:
            raise ValueError(f"TrainConfig: lr must be > 0, got {self.lr}")
        if not 0 <= self.final_lr <= self.lr:
            raise ValueError(
                f"TrainConfig: final_lr must be in [0, lr = {self.lr}], got {self.final_lr}"
            )


@dataclass
class AugmentConfig:
    """Strengths of the training augmentations (ours; the paper does not list them).

    ``crop_scale`` is the range of the crop's area as a fraction of the image; crops keep the
    image's aspect ratio within a factor ``1 + crop_aspect_jitter`` and are resized back to the
    input size. ``rotation_deg`` is the largest rotation either way; ``grayscale`` is the
    probability of dropping colour altogether. Zero disables a step.
    """

    hflip: float = 0.5
    rotation_deg: float = 5.0
    crop_scale: tuple[float, float] = (0.5, 1.0)
    crop_aspect_jitter: float = 0.1
    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.3
    hue: float = 0.02
    grayscale: float = 0.0

    def __post_init__(self) -> None:
        self.crop_scale = tuple(self.crop_scale)  # type: ignore[assignment]
        for name in ("hflip", "grayscale"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"AugmentConfig: {name} is a probability in [0, 1], got {getattr(self, name)}"
                )
        for name in ("rotation_deg", "crop_aspect_jitter", "brightness", "contrast", "saturation"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"AugmentConfig: {name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.hue <= 0.5:
            raise ValueError(f"AugmentConfig: hue must be in [0, 0.5], got {self.hue}")
        lo, hi = self.crop_scale
        if not 0.0 < lo <= hi <= 1.0:
            raise ValueError(
                "AugmentConfig: crop_scale must be (low, high) with 0 < low <= high <= 1, got "
                f"{self.crop_scale}"
            )


@dataclass
class PretrainConfig:
    """Network, data and training settings of a pre-training run (ours, sized so the light
    network pre-trains on a few 160x120 synthetic rooms in minutes on a 2-core CPU)."""

    arch: str = DEFAULT_ARCH
    size: tuple[int, int] = (160, 120)
    label_folder: str = NYU40_FOLDER
    augment: AugmentConfig | None = field(default_factory=AugmentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


def official_augment() -> AugmentConfig:
    """The official code's augmentation (its training datasets' defaults): colour jitter 0.3
    brightness, contrast and saturation and 0.05 hue, rotation up to 10 degrees, a
    horizontal flip half the time, and a crop at the working size of the image scaled by
    1.2 (a fixed 1/1.44 of its area)."""
    crop = 1.0 / 1.2**2
    return AugmentConfig(
        hflip=0.5,
        rotation_deg=10.0,
        crop_scale=(crop, crop),
        crop_aspect_jitter=0.0,
        brightness=0.3,
        contrast=0.3,
        saturation=0.3,
        hue=0.05,
    )


def paper_pretraining() -> PretrainConfig:
    """The paper's network and input size, DeepLabv3-ResNet101 at 320x240 (built with
    ``weights=None``: nothing is downloaded; the paper starts from COCO-pretrained weights and
    the official code from an ImageNet-pretrained backbone, which ``csa seg pretrain
    --weights`` can supply from a local file), trained as the paper says: Adam, the rate
    decayed linearly from 1e-4 to 1e-6 (``--schedule poly`` with this floor is the official
    config's decay)."""
    return PretrainConfig(
        arch=PAPER_ARCH,
        size=PAPER_SIZE,
        augment=official_augment(),
        train=TrainConfig(
            epochs=PAPER_PRETRAIN_EPOCHS,
            batch_size=PAPER_PRETRAIN_BATCH_SIZE,
            lr=PAPER_PRETRAIN_LR,
            schedule="linear",
            final_lr=PAPER_PRETRAIN_FINAL_LR,
        ),
    )


def cpu_pretraining() -> PretrainConfig:
    """Ours: the light network at 160x120, trainable from scratch on a 2-core CPU."""
    return PretrainConfig()


# Pre-training presets by name, as ``csa seg pretrain --preset`` picks them; ``paper`` is the
# network and input size the ``paper`` adaptation preset (csa_core.adapt.config) expects.
PRETRAIN_PRESETS = {"paper": paper_pretraining, "cpu": cpu_pretraining}


def pretrain_preset(name: str) -> PretrainConfig:
    """A fresh pre-training config of the preset ``name`` (``paper`` or ``cpu``)."""
    try:
        return PRETRAIN_PRESETS[name]()
    except KeyError:
        raise ValueError(
            f"unknown pre-training preset {name!r} (choose from {', '.join(PRETRAIN_PRESETS)})"
        ) from None


def paper_network_note(preset: str, arch: str, size: tuple[int, int] | None) -> str | None:
    """A note when an adaptation under the ``paper`` preset runs another network or input
    size than the paper's (``None`` otherwise, and for the other presets)."""
    if preset != "paper" or (arch == PAPER_ARCH and tuple(size or ()) == PAPER_SIZE):
        return None
    shown = f"{size[0]}x{size[1]}" if size else "its own size"
    return (
        f"note: the paper preset's network is {PAPER_ARCH} at {PAPER_SIZE[0]}x{PAPER_SIZE[1]} "
        f"(csa seg pretrain --preset paper); this run adapts {arch} at {shown}"
    )
