"""Losses of the Semantic-NeRF fit (docs/method.md "Fuse in 3D"; paper Eq. 4)."""

from __future__ import annotations

import torch
from torch import Tensor

from csa_core.nerf.config import LossConfig
from csa_core.nerf.rendering import RaySamples, accumulate_along_rays

_LOG_EPS = 1e-8


def _mean(values: Tensor, ray_weight: Tensor | None) -> Tensor:
    """Mean of per-ray ``values``, or their ``ray_weight``-weighted mean (self-normalised): the
    importance weights of rays drawn non-uniformly (``RayBank.balanced_ids``)."""
    if ray_weight is None:
        return values.mean()
    return (values * ray_weight).sum() / ray_weight.sum().clamp_min(_LOG_EPS)


def color_loss(pred: Tensor, target: Tensor, ray_weight: Tensor | None = None) -> Tensor:
    """Mean squared error of rendered vs. observed colour in [0, 1]."""
    return _mean(((pred - target) ** 2).mean(dim=-1), ray_weight)


def depth_loss(pred: Tensor, target: Tensor, ray_weight: Tensor | None = None) -> Tensor:
    """Mean absolute depth error (metres) over the rays where the sensor measured depth (> 0)."""
    valid = target > 0
    if not bool(valid.any()):
        return pred.sum() * 0.0
    w = None if ray_weight is None else ray_weight[valid]
    return _mean(torch.abs(pred[valid] - target[valid]), w)


def semantic_loss(probs: Tensor, labels: Tensor, ray_weight: Tensor | None = None) -> Tensor:
    """Negative log-likelihood of NYU40 ids ``labels`` (R,) under the normalised class
    distributions ``probs`` (R, 40); channel ``k`` is id ``k + 1``, id 0 (unknown) is ignored."""
    known = labels > 0
    if not bool(known.any()):
        return probs.sum() * 0.0
    p = probs[known].gather(1, (labels[known].long() - 1).unsqueeze(1)).squeeze(1)
    w = None if ray_weight is None else ray_weight[known]
    return _mean(-torch.log(p.clamp_min(_LOG_EPS)), w)


def semantic_cross_entropy(
    logits: Tensor, labels: Tensor, ray_weight: Tensor | None = None
) -> Tensor:
    """Semantic-NeRF's original semantic loss (``LossConfig.semantic_form="semantic_nerf"``):
    softmax cross-entropy of NYU40 ids ``labels`` (R,) against the composited logits (R, 40)
    (``rendering.composited_logits``); channel ``k`` is id ``k + 1``, id 0 is ignored."""
    known = labels > 0
    if not bool(known.any()):
        return logits.sum() * 0.0
    ce = torch.nn.functional.cross_entropy(
        logits[known], labels[known].long() - 1, reduction="none"
    )
    w = None if ray_weight is None else ray_weight[known]
    return _mean(ce, w)


def band_consistency_loss(
    logits: Tensor,
    weights: Tensor,
    samples: RaySamples,
    labels: Tensor,
    ray_weight: Tensor | None = None,
) -> Tensor:
    """``LossConfig.semantic_band_consistency``: each ray's cross-entropy of its NYU40 id
    ``labels`` (R,) under every sample's own class distribution (``logits`` (S, C), channel
    ``k`` is id ``k + 1``), averaged with the samples' rendering ``weights`` (S,) normalised
    over the ray; then the (``ray_weight``-weighted) mean over the rays with a label and any
    weight. Unlike the composited terms, no sample can leave a label to another sample of the
    ray: every sample that carries weight is asked for the ray's label."""
    ri = samples.ray_indices
    known = labels > 0
    total = accumulate_along_rays(weights, None, samples)[:, 0]
    rays = known & (total > 0)
    if not bool(rays.any()):
        return logits.sum() * 0.0
    share = weights / total[ri].clamp_min(_LOG_EPS)
    target = (labels.long() - 1).clamp_min(0)[ri]
    ce = torch.nn.functional.cross_entropy(logits, target, reduction="none")
    per_ray = accumulate_along_rays(share * ce, None, samples)[:, 0]
    w = None if ray_weight is None else ray_weight[rays]
    return _mean(per_ray[rays], w)


NEAR_DEPTH = 0.3  # metres: ``near_view_weight`` stops growing below this depth


def near_view_weight(depth: Tensor, power: float, reference: float) -> Tensor:
    """Per-ray weight ``(reference / z) ** power`` of the semantic loss, ``z`` the measured depth
    (at least ``NEAR_DEPTH``); rays without depth (0) weigh 1
    (``LossConfig.semantic_depth_power``)."""
    z = depth.clamp_min(NEAR_DEPTH)
    w = (reference / z) ** power
    return torch.where(depth > 0, w, torch.ones_like(w))


def free_space_loss(
    weights: Tensor, in_front: Tensor, samples: RaySamples, ray_weight: Tensor | None = None
) -> Tensor:
    """Mean over rays of the rendering weight that falls on samples ``in_front`` (S,) of the
    measured surface: carves the free space that depth-guided sampling visits only sparsely.
    ``in_front`` may be fractional: a per-sample weight of the term."""
    w = accumulate_along_rays(weights * in_front, None, samples).squeeze(-1)
    return _mean(w, ray_weight)


def psnr(mse: Tensor | float) -> float:
    """Peak signal-to-noise ratio (dB) of colours in [0, 1] from their mean squared error."""
    mse = float(mse)
    return float("inf") if mse <= 0 else -10.0 * float(torch.log10(torch.tensor(mse)))


def total_loss(
    out: dict[str, Tensor], batch: dict[str, Tensor], cfg: LossConfig
) -> dict[str, Tensor]:
    """Weighted sum of the three losses; returns every term and ``loss``. The semantic term
    is ``cfg.semantic_form``'s: :func:`semantic_loss` of ``out["semantics"]`` (paper) or
    :func:`semantic_cross_entropy` of ``out["semantic_logits"]`` (Semantic-NeRF). A batch with
    ``ray_weight`` (R,) averages every term over rays with those weights; ``semantic_weight``
    (R,) takes its place for the semantic term (``NerfTrainer.semantic_weights``)."""
    rw = batch.get("ray_weight")
    terms = {"color": color_loss(out["rgb"], batch["rgb"], rw)}
    total = cfg.color * terms["color"]
    if cfg.depth > 0 and "depth" in batch:
        terms["depth"] = depth_loss(out["depth"], batch["depth"], rw)
        total = total + cfg.depth * terms["depth"]
    if cfg.semantic > 0 and "labels" in batch and "semantics" in out:
        sw = batch.get("semantic_weight", rw)
        if cfg.semantic_form == "semantic_nerf":
            if "semantic_logits" not in out:
                raise ValueError(
                    "loss.semantic_form=semantic_nerf needs the composited 'semantic_logits'"
                )
            terms["semantic"] = semantic_cross_entropy(out["semantic_logits"], batch["labels"], sw)
        else:
            terms["semantic"] = semantic_loss(out["semantics"], batch["labels"], sw)
        total = total + cfg.semantic * terms["semantic"]
    if "band_consistency" in out:  # weighed against the semantic term
        terms["band_consistency"] = out["band_consistency"]
        total = total + cfg.semantic * cfg.semantic_band_consistency * terms["band_consistency"]
    if cfg.free_space > 0 and "free_space" in out:
        terms["free_space"] = out["free_space"]
        total = total + cfg.free_space * terms["free_space"]
    terms["loss"] = total
    return terms
