"""Volume rendering on packed samples (nerfacc-style functional core).

Samples of all rays are packed into flat tensors: ``ray_indices`` (S,) says which ray each
sample belongs to, ``t_starts``/``t_ends`` (S,) its interval along the ray; samples of one ray
are contiguous and sorted by ``t``. The renderer knows nothing of colour, depth or classes:
``accumulate_along_rays`` sums ``weights * values`` per ray for any number of channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class RaySamples:
    """Packed samples: ``ray_indices`` (S,) int64, ``t_starts`` / ``t_ends`` (S,) along unit-z
    rays."""

    ray_indices: Tensor
    t_starts: Tensor
    t_ends: Tensor
    num_rays: int
    per_ray: int | None = None  # set when every ray has exactly this many samples (dense layout)
    # (S, F): values the sampler computed at each sample on its way (the rendering march's
    # field features, ``SemanticNerf.render_rays``), so they need not be computed again; None
    # when it computed none.
    features: Tensor | None = None

    @property
    def t_mids(self) -> Tensor:
        return 0.5 * (self.t_starts + self.t_ends)

    def __len__(self) -> int:
        return int(self.ray_indices.shape[0])


# Optical depths are capped at this before they are summed into transmittances: exp(-100) is
# below float32's smallest normal number, so the transmittance behind such a sample is zero
# either way, and the cap keeps one near-opaque sample (a density of 1e12 per metre) from
# swamping the sums of the samples after it. Without it, ``cumsum - value`` cancelled: a
# sample of optical depth 1e8 got a transmittance of exp(+-16) in float32, and a fit from
# views spread at random through a room turned every sample opaque within 200 steps
# (benchmarks/results/fusion.md "Opaque everywhere: a cancelling sum, not thin parts").
MAX_OPTICAL_DEPTH = 100.0


def exclusive_cumsum(values: Tensor, dim: int = -1) -> Tensor:
    """Sum of the earlier entries along ``dim`` (0 for the first), without subtracting each
    entry from an inclusive sum (which cancels when one entry dwarfs the rest)."""
    inclusive = torch.cumsum(values, dim=dim)
    zero = torch.zeros_like(inclusive.narrow(dim, 0, 1))
    return torch.cat([zero, inclusive.narrow(dim, 0, inclusive.shape[dim] - 1)], dim=dim)


def exclusive_sum_along_rays(values: Tensor, samples: RaySamples) -> Tensor:
    """Per-sample sum of ``values`` over the earlier samples of the same ray. Exact for the
    dense layout; the packed one subtracts float64 running sums, so ``values`` should be
    bounded (``render_weights`` caps optical depths at :data:`MAX_OPTICAL_DEPTH`)."""
    if samples.per_ray is not None:
        v = values.view(samples.num_rays, samples.per_ray)
        return exclusive_cumsum(v, dim=1).reshape(-1)
    if values.numel() == 0:
        return values
    # Packed: one global cumulative sum in float64, minus its value at each ray's start.
    inclusive = torch.cumsum(values.double(), dim=0)
    exclusive = inclusive - values.double()
    ri = samples.ray_indices
    first = torch.ones_like(ri, dtype=torch.bool)
    first[1:] = ri[1:] != ri[:-1]
    start_of = exclusive[first]  # exclusive sum at the first sample of each ray with samples
    seg = torch.cumsum(first.long(), dim=0) - 1
    return (exclusive - start_of[seg]).to(values.dtype)


def render_weights(
    sigmas: Tensor, samples: RaySamples, ray_scale: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Volume-rendering weights ``w_i = T_i * alpha_i`` with ``alpha_i = 1 - exp(-sigma_i * dl_i)``.

    ``dl_i`` is the interval length in world units: ``(t_end - t_start) * ray_scale`` where
    ``ray_scale`` (num_rays,) is the norm of each ray's direction (unit-z rays are longer than
    one unit per unit of ``t`` off the optical axis). Returns ``(weights, transmittance, alphas)``,
    each (S,).
    """
    dl = samples.t_ends - samples.t_starts
    if ray_scale is not None:
        dl = dl * ray_scale[samples.ray_indices]
    sigma_dt = sigmas * dl
    alphas = 1.0 - torch.exp(-sigma_dt)
    optical = exclusive_sum_along_rays(sigma_dt.clamp(max=MAX_OPTICAL_DEPTH), samples)
    transmittance = torch.exp(-optical)
    return transmittance * alphas, transmittance, alphas


def accumulate_along_rays(weights: Tensor, values: Tensor | None, samples: RaySamples) -> Tensor:
    """Sum ``weights * values`` over each ray: ``(S,)`` x ``(S, C)`` -> ``(num_rays, C)``.

    With ``values=None`` the weights themselves are summed (the opacity), shaped (num_rays, 1).
    Rays without samples get zeros.
    """
    src = weights.unsqueeze(-1) if values is None else weights.unsqueeze(-1) * values
    if samples.per_ray is not None:
        return src.view(samples.num_rays, samples.per_ray, -1).sum(dim=1)
    out = src.new_zeros(samples.num_rays, src.shape[-1])
    return out.index_add_(0, samples.ray_indices, src)


def normalized_class_probabilities(
    weights: Tensor, logits: Tensor, samples: RaySamples, eps: float = 1e-10
) -> Tensor:
    """Paper Eq. 3: per-sample softmax weighted by the (detached) rendering weights, summed along
    the ray and normalised to sum to one -> ``(num_rays, num_classes)``.

    The weights are detached so that the semantic loss cannot move the density.
    """
    acc = accumulate_along_rays(weights.detach(), torch.softmax(logits, dim=-1), samples)
    return acc / (acc.sum(dim=-1, keepdim=True) + eps)


def composited_logits(weights: Tensor, logits: Tensor, samples: RaySamples) -> Tensor:
    """Semantic-NeRF's semantic map: the per-sample logits summed along the ray with the
    (detached) rendering weights -> ``(num_rays, num_classes)``; its softmax is the class
    distribution and its cross-entropy the original loss (``LossConfig.semantic_form``)."""
    return accumulate_along_rays(weights.detach(), logits, samples)


def class_distribution(
    weights: Tensor, logits: Tensor, samples: RaySamples, form: str = "paper"
) -> tuple[Tensor, Tensor | None]:
    """The rendered class distribution (R, C) of ``LossConfig.semantic_form`` ``form`` and,
    for ``semantic_nerf``, the composited logits it is the softmax of (``None`` for
    ``paper``, whose distribution is :func:`normalized_class_probabilities`). A ray without
    rendering weight has no class distribution in either form: all zeros (the softmax of its
    all-zero composited logits would be uniform), so its confidence is 0."""
    if form == "semantic_nerf":
        composited = composited_logits(weights, logits, samples)
        weighted = accumulate_along_rays(weights.detach(), None, samples) > 0
        return torch.softmax(composited, dim=-1) * weighted, composited
    return normalized_class_probabilities(weights, logits, samples), None
