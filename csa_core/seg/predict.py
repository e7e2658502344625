"""Label images with a segmentation network and score it on a scene's views."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.device import resolve_device
from csa_core.errors import CSAInputError
from csa_core.eval.miou import ConfusionMatrix
from csa_core.seg.transforms import image_to_tensor, to_float_image

Images = np.ndarray | Sequence[np.ndarray]


def as_image_list(images: Images) -> tuple[list[np.ndarray], bool]:
    """Images as a list of (H, W, 3) arrays, and whether a single image was given."""
    if isinstance(images, np.ndarray) and images.ndim == 3:
        return [images], True
    if isinstance(images, np.ndarray) and images.ndim != 4:
        raise ValueError(f"expected (H, W, 3) or (N, H, W, 3) images, got shape {images.shape}")
    return list(images), False


@torch.no_grad()
def predict_logits(
    model: nn.Module,
    images: Images,
    batch_size: int = 8,
    device: str | torch.device | None = None,
    size: tuple[int, int] | None = None,
) -> torch.Tensor:
    """(N, C, H, W) float32 CPU logits of uint8 RGB images, at the images' own size.

    ``size`` (width, height) runs the network at another resolution and resizes the logits
    back bilinearly. The model is moved to ``device`` (auto: CUDA if available) and run in
    eval mode; its train/eval mode is restored afterwards.
    """
    batch, _ = as_image_list(images)
    if not batch:
        raise ValueError("predict: no images")
    shape = batch[0].shape
    if any(img.shape != shape for img in batch):
        raise ValueError("predict: all images must have the same size")
    dev = resolve_device(device)
    was_training = model.training
    model.to(dev).eval()
    out: list[torch.Tensor] = []
    if batch_size < 1:
        raise ValueError(f"predict: batch_size must be >= 1, got {batch_size}")
    try:
        for start in range(0, len(batch), batch_size):
            x = torch.stack([image_to_tensor(img) for img in batch[start : start + batch_size]]).to(
                dev
            )
            x = to_float_image(x)
            if size is not None and (size[0], size[1]) != (shape[1], shape[0]):
                x = F.interpolate(
                    x, size=(size[1], size[0]), mode="bilinear", align_corners=False, antialias=True
                )
            logits = model(x)
            if logits.shape[-2:] != shape[:2]:
                logits = F.interpolate(logits, size=shape[:2], mode="bilinear", align_corners=False)
            out.append(logits.float().cpu())
    finally:
        model.train(was_training)
    return torch.cat(out)


def logits_to_labels(logits: torch.Tensor) -> np.ndarray:
    """Arg-max channel k -> NYU40 id k + 1, as uint8 (never 0)."""
    return (logits.argmax(1) + 1).to(torch.uint8).numpy()


def predict_labels(
    model: nn.Module,
    images: Images,
    batch_size: int = 8,
    device: str | torch.device | None = None,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """NYU40 ids (1..40, uint8) for one (H, W, 3) image -> (H, W), or for N images -> (N, H, W).

    Batched; see :func:`predict_logits` for ``device`` and ``size``.
    """
    batch, single = as_image_list(images)
    if batch_size < 1:
        raise ValueError(f"predict: batch_size must be >= 1, got {batch_size}")
    # Arg-max per chunk: the logits of a whole scene would hold 40 floats per pixel.
    chunks = [
        logits_to_labels(predict_logits(model, batch[i : i + batch_size], batch_size, device, size))
        for i in range(0, len(batch), batch_size)
    ]
    labels = np.concatenate(chunks) if chunks else np.zeros((0,), np.uint8)
    return labels[0] if single else labels


def predict_scene(
    model: nn.Module,
    scene: Scene,
    split: str = "all",
    batch_size: int = 8,
    device: str | torch.device | None = None,
    size: tuple[int, int] | None = None,
) -> dict[str, np.ndarray]:
    """``{frame name: NYU40 label map}`` for the frames of ``split``, ready for a label folder."""
    frames = scene.split(split)
    labels = predict_labels(model, [f.color for f in frames], batch_size, device, size)
    return {f.name: lab for f, lab in zip(frames, labels, strict=True)}


def evaluate_scene(
    model: nn.Module,
    scene: Scene,
    split: str = "val",
    label_folder: str = NYU40_FOLDER,
    batch_size: int = 8,
    device: str | torch.device | None = None,
    size: tuple[int, int] | None = None,
) -> ConfusionMatrix:
    """Confusion matrix of the model's predictions on the ``split`` views against
    ``label_folder``."""
    frames = scene.split(split)
    missing = [f.name for f in frames if label_folder not in f.labels]
    if missing:
        where = scene.root / label_folder if scene.root is not None else f"scene {scene.name}"
        raise CSAInputError(
            where, f"no '{label_folder}' labels for frame(s) {', '.join(missing[:5])}"
        )
    matrix = ConfusionMatrix()
    if not frames:
        return matrix
    preds = predict_labels(model, [f.color for f in frames], batch_size, device, size)
    for frame, pred in zip(frames, preds, strict=True):
        matrix.update(pred, frame.labels[label_folder])
    return matrix
