"""Volume rendering on packed samples: weights, transmittance, generic accumulation."""

from __future__ import annotations

import math

import torch

from csa_core.nerf.rendering import (
    RaySamples,
    accumulate_along_rays,
    exclusive_sum_along_rays,
    normalized_class_probabilities,
    render_weights,
)


def _packed(counts: list[int], length: float = 2.0) -> RaySamples:
    ri, ts, te = [], [], []
    for r, n in enumerate(counts):
        edges = torch.linspace(0.0, length, n + 1)
        ri.append(torch.full((n,), r))
        ts.append(edges[:-1])
        te.append(edges[1:])
    return RaySamples(torch.cat(ri), torch.cat(ts), torch.cat(te), len(counts))


def test_constant_density_gives_beer_lambert_opacity():
    samples = _packed([7, 1, 30])
    sigma = torch.full((len(samples),), 0.8)
    weights, trans, _ = render_weights(sigma, samples)
    opacity = accumulate_along_rays(weights, None, samples).squeeze(-1)
    torch.testing.assert_close(
        opacity, torch.full((3,), 1 - math.exp(-0.8 * 2.0)), rtol=1e-5, atol=1e-6
    )
    # Transmittance at the first sample of every ray is 1.
    first = torch.tensor([0, 7, 8])
    torch.testing.assert_close(trans[first], torch.ones(3))


def test_ray_scale_lengthens_intervals():
    samples = _packed([4, 4])
    sigma = torch.full((8,), 0.5)
    w1, _, _ = render_weights(sigma, samples, ray_scale=torch.tensor([1.0, 2.0]))
    op = accumulate_along_rays(w1, None, samples).squeeze(-1)
    torch.testing.assert_close(op, torch.tensor([1 - math.exp(-1.0), 1 - math.exp(-2.0)]))


def test_packed_and_dense_layouts_agree_for_any_channel_count():
    g = torch.Generator().manual_seed(0)
    n_rays, k = 5, 6
    packed = _packed([k] * n_rays)
    dense = RaySamples(packed.ray_indices, packed.t_starts, packed.t_ends, n_rays, per_ray=k)
    sigma = torch.rand(n_rays * k, generator=g) * 3
    for channels in (1, 3, 40):
        values = torch.rand(n_rays * k, channels, generator=g)
        wp, _, _ = render_weights(sigma, packed)
        wd, _, _ = render_weights(sigma, dense)
        torch.testing.assert_close(wp, wd, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(
            accumulate_along_rays(wp, values, packed),
            accumulate_along_rays(wd, values, dense),
            rtol=1e-5,
            atol=1e-6,
        )


def test_exclusive_sum_resets_at_every_ray():
    samples = _packed([3, 2, 4])
    values = torch.arange(1.0, 10.0)
    got = exclusive_sum_along_rays(values, samples)
    torch.testing.assert_close(got, torch.tensor([0.0, 1, 3, 0, 4, 0, 6, 13, 21]))


def test_rays_without_samples_accumulate_to_zero():
    samples = RaySamples(
        torch.tensor([0, 0, 2]), torch.tensor([0.0, 1, 0]), torch.tensor([1.0, 2, 1]), 4
    )
    w, _, _ = render_weights(torch.ones(3), samples)
    acc = accumulate_along_rays(w, torch.ones(3, 2), samples)
    assert acc.shape == (4, 2)
    assert acc[1].abs().sum() == 0 and acc[3].abs().sum() == 0


def test_class_probabilities_are_normalised_and_do_not_carry_gradient_to_weights():
    samples = _packed([5, 5])
    sigma = torch.rand(10, requires_grad=True)
    logits = torch.randn(10, 40, requires_grad=True)
    w, _, _ = render_weights(sigma, samples)
    probs = normalized_class_probabilities(w, logits, samples)
    torch.testing.assert_close(probs.sum(-1), torch.ones(2))
    (-torch.log(probs[:, 3])).sum().backward()
    assert sigma.grad is None or sigma.grad.abs().sum() == 0
    assert logits.grad.abs().sum() > 0


def test_a_near_opaque_sample_keeps_the_transmittance_in_front_of_it_exact():
    # Optical depths 0.1, 0.2, 1e9, 0.3 along one ray, in both layouts and in a batch where
    # another ray holds the huge value: the sum in front of the huge sample must not be taken
    # as (sum including it) - (it), which cancels in float32 and gave exp(+-16).
    for per_ray in (4, None):
        samples = RaySamples(
            torch.tensor([0, 0, 0, 0, 1, 1, 1, 1]),
            torch.tensor([0.0, 1.0, 2.0, 3.0] * 2),
            torch.tensor([1.0, 2.0, 3.0, 4.0] * 2),
            2,
            per_ray=per_ray,
        )
        sigma = torch.tensor([0.1, 0.2, 1e9, 0.3, 0.1, 0.2, 0.3, 0.4])
        weights, trans, _ = render_weights(sigma, samples)
        expected = torch.exp(-torch.tensor([0.0, 0.1, 0.3, 0.3 + 1e9]))
        torch.testing.assert_close(trans[:4], expected)
        torch.testing.assert_close(trans[4:], torch.exp(-torch.tensor([0.0, 0.1, 0.3, 0.6])))
        # The ray is opaque at its third sample: all its weight up to there, none after.
        torch.testing.assert_close(weights[:4].sum(), torch.tensor(1.0))
        assert float(weights[3]) < 1e-40 and torch.isfinite(weights).all()
