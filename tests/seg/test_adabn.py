"""AdaBN touches BatchNorm statistics only, and moves them to the target images' statistics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from csa_core.seg.adabn import _batches, adapt_batchnorm, batchnorm_layers
from csa_core.seg.models import build_model

BN_BUFFERS = ("running_mean", "running_var", "num_batches_tracked")


def _snapshot(model: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _target_images(n: int = 6, seed: int = 0) -> list[np.ndarray]:
    """Dark, blue-tinted images: a covariate shift from the default initialisation."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 60, size=(n, 48, 64, 3))
    base[..., 2] += 150
    return [img.astype(np.uint8) for img in base]


@pytest.fixture
def model():
    torch.manual_seed(0)
    m = build_model()
    m.train()
    with torch.no_grad():  # source statistics from bright random images
        for _ in range(3):
            m(torch.rand(4, 3, 48, 64))
    return m.eval()


def test_only_batchnorm_statistics_change(model):
    before = _snapshot(model)
    params_before = {k: p.detach().clone() for k, p in model.named_parameters()}
    momenta = [bn.momentum for bn in batchnorm_layers(model)]
    count = adapt_batchnorm(model, _target_images(), batch_size=4, device="cpu")
    after = _snapshot(model)
    assert count == len(batchnorm_layers(model)) > 0
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed, "AdaBN changed nothing"
    assert all(k.rsplit(".", 1)[1] in BN_BUFFERS for k in changed)
    assert {k for k in before if k.endswith("running_mean")} <= changed
    for k, p in model.named_parameters():
        assert torch.equal(p, params_before[k]), k
    assert [bn.momentum for bn in batchnorm_layers(model)] == momenta
    assert not model.training and not any(m.training for m in model.modules())


def test_statistics_move_to_the_target_images(model):
    images = _target_images(n=8)
    x = torch.stack([torch.from_numpy(i).permute(2, 0, 1) for i in images]).float() / 255
    first_conv, first_bn = model.net.backbone["0"][0], model.net.backbone["0"][1]
    with torch.no_grad():
        feats = first_conv((x - model.mean) / model.std)
    target_mean = feats.mean(dim=(0, 2, 3))
    target_var = feats.var(dim=(0, 2, 3))
    gap_before = (first_bn.running_mean - target_mean).abs().mean().item()
    adapt_batchnorm(model, images, batch_size=4, device="cpu")
    gap_after = (first_bn.running_mean - target_mean).abs().mean().item()
    assert gap_after < 1e-4 < gap_before
    # Averaged per-batch variances of two equal batches: close to the pooled variance.
    assert torch.allclose(first_bn.running_var, target_var, rtol=0.1)
    assert first_bn.num_batches_tracked.item() == 2


def test_training_mode_is_restored(model):
    model.train()
    adapt_batchnorm(model, _target_images(), device="cpu")
    assert all(m.training for m in model.modules())


def test_adabn_makes_predictions_shift_invariant_for_a_bn_network():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 4, 1), nn.BatchNorm2d(4))
    source = torch.rand(8, 3, 6, 6)
    net.train()
    with torch.no_grad():
        net(source)
    net.eval()
    images = [
        ((source[i] + 0.5).clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy()
        for i in range(8)
    ]
    adapt_batchnorm(net, images, batch_size=8, device="cpu")
    with torch.no_grad():
        x = torch.stack([torch.from_numpy(i).permute(2, 0, 1) for i in images]).float() / 255
        out = net(x)
    assert out.mean(dim=(0, 2, 3)).abs().max() < 1e-4


def test_batches_never_hold_a_single_image():
    assert [s.stop - s.start for s in _batches(9, 4)] == [4, 5]
    assert [s.stop - s.start for s in _batches(8, 4)] == [4, 4]
    assert [s.stop - s.start for s in _batches(3, 2)] == [3]


def test_too_few_images_is_an_error(model):
    with pytest.raises(ValueError, match="at least 2 images"):
        adapt_batchnorm(model, _target_images(n=1))
    with pytest.raises(ValueError, match="batch_size"):
        adapt_batchnorm(model, _target_images(), batch_size=1)
