"""One step of a continual run, and what the run keeps between steps.

Every caller adapts through :func:`continual_step`: ``csa adapt`` and ``csa experiment``
(through :func:`csa_core.adapt.continual.run_continual`, which also scores R) and the
service's adapt job, which builds a :class:`~csa_core.adapt.methods.ContinualState` from its stores,
calls the step once and registers what the state now holds. A step of our method renders the replay
buffer from the memory bank (at most ``config.replay.max_render_samples`` samples per ray), adapts
with it and the pre-training slice, banks the scene's NeRF, and (with ``config.adabn`` and
``config.pool_batchnorm``) records the network's BatchNorm statistics for the scene and runs
the network with the pooled statistics of every recorded scene (:mod:`csa_core.adapt.bn_memory`).
A scene the collapse guard skipped leaves no NeRF and no BatchNorm record behind; a scene
whose NeRF labels it rejected (the network trained on its own predictions instead) leaves
its BatchNorm record but no NeRF, so nothing of it is replayed later.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

from torch import nn

from csa_core.adapt.config import MODES, AdaptConfig
from csa_core.adapt.finetune import evaluate
from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.methods import METHODS, ContinualState, check_method, make_method
from csa_core.adapt.replay import PretrainReplay
from csa_core.data.scene import Scene
from csa_core.progress import ProgressCallback
from csa_core.seg.models import SegmentationNet


def continual_step(
    state: ContinualState,
    model: SegmentationNet,
    scene: Scene,
    on_progress: ProgressCallback | None = None,
) -> dict[str, Any]:
    """Adapt ``model`` in place to ``scene`` (its labels are read only to score) with the
    state's method, update the state's memories, and return the step's record.

    For our method: replay rendered from ``state.bank`` (every scene in it but ``scene``),
    :func:`~csa_core.adapt.modes.adapt_one_step` with the replay, the pre-training slice
    and the prior entropy, the scene's NeRF added to the bank when the guard accepted its
    labels. Then, when the state pools BatchNorm statistics, the reported network's
    statistics are recorded for ``scene`` (not after a skip) and the reported network (and
    ``model``, when that is another one: CoTTA's student) run with the mixture of all records.
    The record has the method's fields plus ``batchnorm_pooled`` (the scenes in the mixture,
    ``None`` without pooling) and ``memory_bytes``
    (:meth:`~csa_core.adapt.methods.ContinualState.memory_bytes`).
    ``on_progress`` hears the adaptation (:mod:`csa_core.progress`).
    """
    record = state.method.step(state, model, scene, on_progress)
    pooled = None
    if state.batchnorm is not None:
        t = time.perf_counter()
        reported = state.method.reported(model)
        if record.get("trained", True):
            state.batchnorm.add(scene.name, reported)
        state.batchnorm.apply(reported)
        if reported is not model:
            state.batchnorm.apply(model)
        pooled = list(state.batchnorm.scenes)
        record["seconds"] = {**record["seconds"], "batchnorm_pool": time.perf_counter() - t}
    record["batchnorm_pooled"] = pooled
    record["memory_bytes"] = state.memory_bytes()
    return record


def one_step(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    method: str,
    out: str | Path,
    pretrain: PretrainReplay | None = None,
    prior_entropy: float | None = None,
) -> tuple[dict[str, Any], nn.Module]:
    """The one-step protocol: adapt ``model`` (in place) to one scene with ``method``, one of
    :data:`~csa_core.adapt.methods.METHODS` or ``gi_nl``/``ni_nl``/``joint`` for ours in
    that mode, as the first step of a run without BatchNorm pooling (one scene: nothing to
    pool) whose memory bank is ``out/memory``. Returns the step's record with the val/train
    mIoU ``before`` and ``after`` (empty without ground truth), and the reported network
    (the teacher for CoTTA, ``model`` otherwise)."""
    check_method(method, (*METHODS, *MODES))
    if method in MODES:
        config = copy.deepcopy(config)
        config.mode = method
        name = "ours"
    else:
        name = method
    state = ContinualState(
        make_method(name, config),
        bank=MemoryBank(Path(out) / "memory"),
        pretrain=pretrain,
        prior_entropy=prior_entropy,
    )
    before = evaluate(model, scene, config.seg.device)
    record = continual_step(state, model, scene)
    reported = state.method.reported(model)
    record["method"] = method
    record["mode"] = config.mode if name == "ours" else None
    record["before"] = before
    record["after"] = evaluate(reported, scene, config.seg.device)
    record["method_settings"] = state.method.settings()
    return record, reported
