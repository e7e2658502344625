"""Collapse of pseudo-labels, and the guard against it (ours; docs/method.md "Known weaknesses").

On badly exposed scenes or scenes without depth, joint training can drive the NeRF and the
network towards one class: each supervises the other with ever more uniform labels. Three
signals catch it without ground truth, each measured against the previous model's
predictions on the same views: the entropy of the labels' class histogram, the share of
their dominant class, and their agreement with the predictions beyond chance (adaptation
should refine them, not replace them; a noisy network's predictions agree little with any
fusion of them, so raw agreement would penalise exactly the scenes fusion helps most). Fixed bars
set on one family of rooms misfire on another (a real room whose views are 86% wall), so no bar is
absolute.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from csa_core.adapt.config import CollapseConfig
from csa_core.data.nyu40 import NUM_CLASSES

log = logging.getLogger(__name__)

LabelMaps = Mapping[str, np.ndarray] | Iterable[np.ndarray]


def _maps(labels: LabelMaps) -> list[np.ndarray]:
    return list(labels.values()) if isinstance(labels, Mapping) else list(labels)


def class_histogram(labels: LabelMaps) -> np.ndarray:
    """Pixel count per NYU40 id (index 0 = unknown) over all maps."""
    counts = np.zeros(NUM_CLASSES + 1, dtype=np.int64)
    for m in _maps(labels):
        counts += np.bincount(np.asarray(m, dtype=np.int64).ravel(), minlength=NUM_CLASSES + 1)[
            : NUM_CLASSES + 1
        ]
    return counts


def histogram_entropy(counts: np.ndarray) -> float:
    """Entropy (nats) of the class distribution over known pixels (id 0 excluded); 0 when empty."""
    known = np.asarray(counts, dtype=np.float64)[1:]
    total = known.sum()
    if total <= 0:
        return 0.0
    p = known[known > 0] / total
    return max(0.0, float(-(p * np.log(p)).sum()))


def label_entropy(labels: LabelMaps) -> float:
    """Entropy (nats) of the class histogram of label maps."""
    return histogram_entropy(class_histogram(labels))


def dominant_fraction(labels: LabelMaps) -> tuple[int, float]:
    """The most frequent known class and the fraction of known pixels it covers."""
    counts = class_histogram(labels)[1:]
    total = counts.sum()
    if total == 0:
        return 0, 0.0
    k = int(counts.argmax())
    return k + 1, float(counts[k] / total)


def agreement(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> float:
    """Fraction of pixels, known in both, where two label sets (keyed by frame) agree."""
    return agreement_kappa(a, b)[0]


def agreement_kappa(
    a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]
) -> tuple[float, float]:
    """Agreement of two label sets (keyed by frame) over the pixels known in both, and its
    chance-corrected version, Cohen's kappa = (p_o - p_e) / (1 - p_e), where p_e is the
    agreement two independent maps with the same class frequencies would reach: 0 for labels
    unrelated to the others (or collapsed to one class), 1 for identical ones. NaN, NaN
    without common known pixels."""
    same = total = 0
    count_a = np.zeros(NUM_CLASSES + 1, dtype=np.int64)
    count_b = np.zeros(NUM_CLASSES + 1, dtype=np.int64)
    for name, x in a.items():
        if name not in b:
            continue
        y = b[name]
        known = (x > 0) & (y > 0)
        xs, ys = np.asarray(x[known], np.int64), np.asarray(y[known], np.int64)
        same += int((xs == ys).sum())
        total += int(known.sum())
        count_a += np.bincount(xs, minlength=NUM_CLASSES + 1)[: NUM_CLASSES + 1]
        count_b += np.bincount(ys, minlength=NUM_CLASSES + 1)[: NUM_CLASSES + 1]
    if not total:
        return float("nan"), float("nan")
    observed = same / total
    chance = float((count_a / total) @ (count_b / total))
    kappa = 1.0 if chance >= 1.0 else (observed - chance) / (1.0 - chance)
    return observed, kappa


@dataclass
class CollapseReport:
    """What the detector measured and concluded, for the run's log."""

    entropy: float
    reference_entropy: float
    dominant_class: int
    dominant_fraction: float
    dominant_limit: float  # NaN without the previous model's predictions to compare with
    agreement: float
    kappa: float  # the agreement beyond chance (Cohen's kappa)
    collapsed: bool
    reasons: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def detect_collapse(
    labels: Mapping[str, np.ndarray],
    previous: Mapping[str, np.ndarray] | None,
    config: CollapseConfig | None = None,
    prior_entropy: float | None = None,
) -> CollapseReport:
    """Judge label maps ``labels`` against the previous model's predictions ``previous`` on
    the same frames, or, without ``previous`` (judging the predictions themselves), against
    ``prior_entropy`` (the class entropy of the pre-training labels).

    With ``previous``, every bar is relative to the predictions (``CollapseConfig``): the
    labels' entropy against the predictions' entropy, their dominant class against the
    predictions' dominant class, and their agreement with the predictions beyond what their
    class frequencies give by chance (:func:`agreement_kappa`); the prior plays no part. A scene's
    own class mix is so never a collapse: a room whose views are mostly wall, seen so by the
    network, passes; labels that turned most of what the network saw as other classes into one class
    do not. Without ``previous`` the one bar is the entropy against the prior: a network that sees
    one class where the pre-training rooms showed many.
    """
    cfg = config or CollapseConfig()
    entropy = label_entropy(labels)
    cls, frac = dominant_fraction(labels)
    reasons = []
    if previous is None:
        reference = float(prior_entropy) if prior_entropy is not None else float("nan")
        agree = kappa = float("nan")
        dominant_limit = float("nan")
    else:
        reference = label_entropy(previous)
        agree, kappa = agreement_kappa(labels, previous)
        _, previous_frac = dominant_fraction(previous)
        dominant_limit = previous_frac + cfg.max_dominant_gain * (1.0 - previous_frac)
    if math.isfinite(reference) and entropy < cfg.min_entropy_ratio * reference:
        reasons.append(
            f"class entropy {entropy:.2f} < {cfg.min_entropy_ratio:g} x reference {reference:.2f} "
            "nats"
        )
    if math.isfinite(dominant_limit) and frac > dominant_limit:
        reasons.append(
            f"class {cls} covers {100 * frac:.0f}% of the pixels (limit "
            f"{100 * dominant_limit:.0f}%: "
            f"the predictions' dominant class plus {100 * cfg.max_dominant_gain:.0f}% of the rest)"
        )
    if math.isfinite(kappa) and kappa < cfg.min_kappa:
        reasons.append(
            f"agrees with the previous model on {100 * agree:.0f}% of the pixels, kappa "
            f"{kappa:.2f} beyond chance (limit {cfg.min_kappa:g})"
        )
    return CollapseReport(
        entropy=entropy,
        reference_entropy=reference,
        dominant_class=cls,
        dominant_fraction=frac,
        dominant_limit=dominant_limit,
        agreement=agree,
        kappa=kappa,
        collapsed=bool(reasons),
        reasons=reasons,
    )


@dataclass
class GuardDecision:
    """What the guard did at one checkpoint of an adaptation (``stage``)."""

    stage: str
    action: str  # "continue", "fallback_predictions", "stop_joint" or "skip"
    report: CollapseReport

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "action": self.action, "report": self.report.to_dict()}


def guard(
    stage: str,
    report: CollapseReport,
    config: CollapseConfig,
    previous_collapsed: bool,
    in_joint: bool = False,
) -> GuardDecision:
    """Decide what to do about a collapse report, and log the decision.

    Healthy labels: continue. Collapsed NeRF labels during joint rounds: stop the joint
    updates and keep the network from before the collapsed round. Collapsed labels before
    training: fall back to the previous model's own predictions when those are healthy
    (``fallback="predictions"``), else skip the scene (keep the previous network).
    """
    if not config.enabled or not report.collapsed:
        action = "continue"
    elif in_joint:
        action = "stop_joint"
    elif config.fallback == "predictions" and not previous_collapsed:
        action = "fallback_predictions"
    else:
        action = "skip"
    decision = GuardDecision(stage=stage, action=action, report=report)
    if report.collapsed:
        note = action if config.enabled else "guard disabled, continuing"
        log.warning("collapse at %s: %s -> %s", stage, "; ".join(report.reasons), note)
    return decision
