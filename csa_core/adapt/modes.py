"""One-step adaptation to one scene in the config's mode (docs/method.md "Adapt").

``gi_nl`` and ``ni_nl`` fine-tune on the NeRF's labels (:mod:`csa_core.adapt.finetune`),
``joint`` alternates network and NeRF updates (:mod:`csa_core.adapt.joint`); both start
from the same fit and guard (:func:`csa_core.adapt.finetune.begin_step`).
"""

from __future__ import annotations

from csa_core.adapt.config import AdaptConfig
from csa_core.adapt.finetune import OneStepResult, finetune_adapt
from csa_core.adapt.joint import joint_adapt
from csa_core.adapt.replay import PretrainReplay, ReplayBuffer
from csa_core.data.scene import Scene
from csa_core.progress import ProgressCallback
from csa_core.seg.models import SegmentationNet


def adapt_one_step(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    replay: ReplayBuffer | None = None,
    pretrain: PretrainReplay | None = None,
    prior_entropy: float | None = None,
    evaluate_before: bool = True,
    on_progress: ProgressCallback | None = None,
) -> OneStepResult:
    """Adapt ``model`` in place to ``scene`` (its labels are read only to score) with
    ``config.mode``; returns the scores before and after, pseudo-label quality, the guard's
    decisions and timings. The fitted NeRF is in ``result.nerf``, for the memory bank when
    ``result.trained`` (after a ``skip`` the guard rejected its labels; after a
    ``stop_joint`` it is back in its state before the rejected round).

    ``on_progress(message, fraction)`` (:mod:`csa_core.progress`) hears the NeRF fit's steps,
    every fine-tuning epoch (every joint round) and the end. What it raises propagates
    unchanged; ``model`` is then partly trained and should be discarded.
    """
    adapt = joint_adapt if config.mode == "joint" else finetune_adapt
    return adapt(
        model, scene, config, replay, pretrain, prior_entropy, evaluate_before, on_progress
    )
