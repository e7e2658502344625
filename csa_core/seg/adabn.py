"""AdaBN: re-estimate BatchNorm statistics on target-domain images (Li et al., 2016).

After training on rendered views the network is run on camera images, whose colour and
noise statistics differ; recomputing each BatchNorm layer's running mean and variance on
the camera images adapts the network without labels and without touching a weight
(docs/method.md, "Adapt"). Statistics of a single scene are narrower than those of the
training set: a network that leans on absolute colour can lose accuracy under them, so
AdaBN is a choice to measure per setting, not a free gain.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable

import torch
from torch import Tensor, nn
from torch.nn.modules.batchnorm import _BatchNorm

from csa_core.device import resolve_device
from csa_core.seg.predict import Images, as_image_list
from csa_core.seg.transforms import image_to_tensor, to_float_image


def batchnorm_layers(model: nn.Module) -> list[_BatchNorm]:
    """The BatchNorm layers of ``model`` that keep running statistics."""
    return [m for m in model.modules() if isinstance(m, _BatchNorm) and m.track_running_stats]


def _batches(n: int, batch_size: int) -> list[slice]:
    """Split ``n`` items into batches of about ``batch_size``, none of a single item.

    A batch of one image cannot be normalised where a layer sees a 1x1 map (DeepLabv3's
    image-pooling branch), so a trailing single image joins the previous batch.
    """
    bounds = list(range(0, n, batch_size)) + [n]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] == 1:
        bounds.pop(-2)
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


@torch.no_grad()
def recompute_batchnorm(
    model: nn.Module, batches: Iterable[Tensor], device: str | torch.device | None = None
) -> int:
    """Replace every BatchNorm layer's running statistics by their average over ``batches``.

    ``batches`` yields (B, 3, H, W) float images in [0, 1] (B >= 2). Statistics are reset and
    re-accumulated as a cumulative average (``momentum=None``) with only the BatchNorm layers
    in training mode and no gradients, so parameters, other buffers and dropout stay as they
    were; each layer's momentum and every module's mode are restored. Returns the number of
    BatchNorm layers updated (0 if ``batches`` is empty: then nothing changes).
    """
    layers = batchnorm_layers(model)
    iterator = iter(batches)
    first = next(iterator, None)
    if not layers or first is None:
        return 0
    dev = resolve_device(device)
    modes = {m: m.training for m in model.modules()}
    momenta = {bn: bn.momentum for bn in layers}
    model.to(dev).eval()
    try:
        for bn in layers:
            bn.reset_running_stats()
            bn.momentum = None
            bn.train()
        for x in itertools.chain([first], iterator):
            model(x.to(dev))
    finally:
        for bn, momentum in momenta.items():
            bn.momentum = momentum
        for m, training in modes.items():
            m.train(training)
    return len(layers)


def adapt_batchnorm(
    model: nn.Module,
    images: Images,
    batch_size: int = 16,
    device: str | torch.device | None = None,
    seed: int = 0,
) -> int:
    """AdaBN: recompute every BatchNorm layer's statistics on target-domain ``images``.

    ``images``: (H, W, 3) uint8 RGB arrays, at least two; see :func:`recompute_batchnorm`.
    The images are shuffled (with ``seed``) before batching: frames of a video are strongly
    correlated, and batches of consecutive frames would average within-batch variances that
    are far smaller than the variance over all images. Returns the number of BatchNorm layers
    updated. The model is moved to ``device``.
    """
    batch, _ = as_image_list(images)
    if len(batch) < 2:
        raise ValueError(f"adapt_batchnorm: needs at least 2 images, got {len(batch)}")
    if batch_size < 2:
        raise ValueError(f"adapt_batchnorm: batch_size must be >= 2, got {batch_size}")
    order = torch.randperm(len(batch), generator=torch.Generator().manual_seed(seed)).tolist()
    batches = (
        to_float_image(torch.stack([image_to_tensor(batch[i]) for i in order[part]]))
        for part in _batches(len(batch), batch_size)
    )
    return recompute_batchnorm(model, batches, device)
