"""``adapt``: one step of the continual chain, the core's ``csa_core.adapt.step.continual_step``.

``gather`` names the step's inputs in the service's stores: the lineage's newest network and
its BatchNorm memory (a file of that version), the scene (its ground truth, when uploaded, is
read only to score), the NeRFs the lineage's earlier steps banked
(:class:`server.memory_bank.StoredNerf`, read as stored by
:class:`server.memory_bank.StoredNerfMemory`), the lineage root's pre-training scenes and the
labelled scenes adapted to earlier. ``compute`` builds the core's
:class:`~csa_core.adapt.step.ContinualState` from them and takes the one step that ``csa
adapt`` and ``csa experiment`` take, so the same inputs, seed and thread count give the same
network on a CPU (on CUDA, atomic additions in the hash grid's backward pass and cuDNN make
two runs agree only statistically); it scores the networks with the core's
``csa_core.adapt.continual.val_mious``. ``register`` writes the outputs in one transaction:
the new model version (parent = the version it started from) with the BatchNorm memory after
the step, the scene's NeRF in the memory bank (unless the collapse guard skipped the scene),
and the R-matrix entries this step makes computable (the new version on every labelled scene
of the lineage, the previous version and the root on this scene).

Jobs of one lineage run one after another (the worker's lineage lock), so each step starts
from the version the previous step made.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db.models import Evaluation, Job, ModelVersion
from server.db.models import Scene as SceneRow
from server.errors import invalid
from server.jobs.context import JobContext
from server.jobs.inputs import (
    ModelInput,
    SceneInput,
    gather_model,
    gather_scene,
    load_scene,
    model_file,
    torch_device,
)
from server.jobs.phases import ApiNode
from server.lookups import get_model, get_scene
from server.memory_bank import StoredNerf, StoredNerfMemory, add_nerf, lineage_nerfs
from server.registry import BATCHNORM_FILE, CHECKPOINT_FILE, lineage_chain, register_checkpoint
from server.schemas.jobs import AdaptParams

MAX_NAME_LENGTH = ModelVersion.__table__.c.name.type.length  # of a model version's name


def prepare(session: Session, params: AdaptParams, job: Job) -> tuple[dict[str, Any], str | None]:
    from csa_core.adapt import preset

    scene = get_scene(session, params.scene)
    if scene.intrinsics is None:
        raise invalid("params.scene", f"scene {scene.name!r} has no frames")
    model = get_model(session, params.model)
    try:
        preset(params.preset)
    except ValueError as e:
        raise invalid("params.preset", str(e)) from None
    normalized = {
        "scene_id": scene.id,
        "lineage": model.lineage,
        "preset": params.preset,
        "mode": params.mode,
        "seed": params.seed,
        "make_current": params.make_current,
    }
    return normalized, model.lineage


def step_name(session: Session, lineage: str, step: int) -> str:
    """The name of the version a lineage's ``step``-th adaptation registers: ``<lineage>-step<n>``,
    the lineage cut to fit the names' length, and ``.2``, ``.3``... after it while another
    version holds the name (clients name their uploads and pre-trainings freely)."""
    for k in itertools.count(1):
        suffix = f"-step{step}" + (f".{k}" if k > 1 else "")
        name = lineage[: MAX_NAME_LENGTH - len(suffix)] + suffix
        if session.scalar(select(ModelVersion.id).where(ModelVersion.name == name)) is None:
            return name
    raise AssertionError("unreachable")


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


@dataclass
class AdaptInputs:
    lineage: str
    preset: str
    mode: str | None
    seed: int
    make_current: bool | None
    base: ModelInput  # the lineage's newest version: its checkpoint and BatchNorm memory
    root: ModelInput | None  # the lineage's root, when this step scores it on the scene
    target: SceneInput
    pretrain_scenes: list[SceneInput]  # the lineage root's pre-training scenes
    earlier: list[SceneInput]  # labelled scenes adapted to earlier in the lineage, oldest first
    nerfs: list[StoredNerf]  # the NeRFs the lineage's earlier steps banked


@dataclass
class Score:
    model_id: int | None  # None: the version this step makes
    scene_id: int
    miou: float | None  # validation mIoU


@dataclass
class AdaptOutputs:
    lineage: str
    make_current: bool | None
    parent_id: int
    parent_name: str
    arch: str
    scene_id: int
    checkpoint: Path
    batchnorm: Path | None  # the BatchNorm memory after the step
    nerf: Path | None  # the scene's NeRF, unless the collapse guard skipped the scene
    nerf_preset: str
    nerf_quality: dict[str, Any]
    metrics: dict[str, Any]
    meta: dict[str, Any]  # task, preset, mode and the step's record
    scores: list[Score]


def gather(session: Session, params: dict[str, Any], node: ApiNode) -> AdaptInputs:
    lineage, target_id = params["lineage"], params["scene_id"]
    chain = lineage_chain(session, lineage)
    if not chain:
        raise LookupError(f"lineage {lineage!r} has no model versions")
    root, base = chain[0], chain[-1]
    target = gather_scene(session, node.store, target_id)
    earlier: list[int] = []  # scenes adapted to earlier in the lineage, oldest first
    for m in chain[1:]:
        sid = m.adapted_scene_id
        if (
            sid is not None
            and sid != target_id
            and sid not in earlier
            and session.get(SceneRow, sid) is not None
        ):
            earlier.append(sid)
    pretrain_ids = [
        int(i)
        for i in (root.meta or {}).get("scene_ids", [])
        if session.get(SceneRow, int(i)) is not None
    ]
    score_root = target.labelled and root.id != base.id
    if score_root:  # the root's score on the scene, unless an earlier job made it
        have = select(Evaluation.id).where(
            Evaluation.model_version_id == root.id,
            Evaluation.scene_id == target_id,
            Evaluation.split == "val",
        )
        score_root = session.scalar(have.limit(1)) is None
    return AdaptInputs(
        lineage=lineage,
        preset=params["preset"],
        mode=params.get("mode"),
        seed=params.get("seed", 0),
        make_current=params["make_current"],
        base=gather_model(session, node.store, base.id, (CHECKPOINT_FILE, BATCHNORM_FILE)),
        root=gather_model(session, node.store, root.id) if score_root else None,
        target=target,
        pretrain_scenes=[gather_scene(session, node.store, sid) for sid in pretrain_ids],
        earlier=[
            sc for sc in (gather_scene(session, node.store, sid) for sid in earlier) if sc.labelled
        ],
        nerfs=lineage_nerfs(session, node.store, chain[1:], exclude_scene_id=target_id),
    )


def compute(inputs: AdaptInputs, workdir: Path, ctx: JobContext) -> AdaptOutputs:
    from csa_core.adapt.continual import val_mious
    from csa_core.adapt.step import continual_step
    from csa_core.seg import load_checkpoint

    device = torch_device(ctx)
    base, target = inputs.base, inputs.target
    ctx.progress(0.02, f"loading {base.name}", force=True)
    net, card = load_checkpoint(model_file(base, workdir), device=device or "cpu")
    size = tuple(card.input_size) if card.input_size else None
    scene = load_scene(target, workdir, ground_truth=target.labelled, size=size)
    config, state, bank = _start(inputs, workdir, device, size)

    scores: list[Score] = []
    if target.labelled:
        ctx.progress(0.1, f"scoring {base.name} on {target.name} before adapting", force=True)
        scores.append(Score(base.id, target.id, _finite(val_mious(net, [scene], device)[0])))

    replay = f"{len(inputs.nerfs)} earlier scene(s) to replay"
    message = f"adapting to {target.name} ({config.preset}, {config.mode}; {replay})"
    ctx.progress(0.15, message, force=True)
    record = continual_step(state, net, scene, on_progress=ctx.core_progress(0.15, 0.85))
    ctx.progress(0.85, "scoring the adapted network", force=True)
    scores += _score_adapted(inputs, workdir, ctx, net, scene, size, device)
    if inputs.root is not None:
        root_net, _ = load_checkpoint(model_file(inputs.root, workdir), device=device or "cpu")
        scores.append(
            Score(inputs.root.id, target.id, _finite(val_mious(root_net, [scene], device)[0]))
        )
        del root_net

    ctx.progress(0.95, "saving the network, its BatchNorm memory and the NeRF", force=True)
    return _save(inputs, workdir, config, state, bank, net, card, record, scores)


def _start(
    inputs: AdaptInputs, workdir: Path, device: str | None, size: tuple[int, ...] | None
) -> tuple[Any, Any, StoredNerfMemory]:
    """The core's state before the step: the configuration, the bank of earlier NeRFs, the
    pre-training scenes and the BatchNorm memory."""
    from csa_core.adapt import preset
    from csa_core.adapt.bn_memory import BatchNormMemory
    from csa_core.adapt.step import ContinualState
    from csa_core.experiments.inputs import seeded

    config = seeded(preset(inputs.preset), inputs.seed)
    if inputs.mode:
        config.mode = inputs.mode
    config.seg.device = device
    pretrain_scenes = [
        load_scene(sc, workdir, ground_truth=True, size=size) for sc in inputs.pretrain_scenes
    ]
    has_batchnorm = BATCHNORM_FILE in inputs.base.files
    batchnorm = (
        BatchNormMemory.load(model_file(inputs.base, workdir, BATCHNORM_FILE))
        if has_batchnorm
        else None
    )
    bank = StoredNerfMemory(inputs.nerfs, workdir / "memory")
    state = ContinualState.start(
        config, "ours", bank=bank, pretrain_scenes=pretrain_scenes, batchnorm=batchnorm
    )
    return config, state, bank


def _score_adapted(
    inputs: AdaptInputs,
    workdir: Path,
    ctx: JobContext,
    net: Any,
    scene: Any,
    size: Any,
    device: str | None,
) -> list[Score]:
    """The adapted network's scores on the scene and on the labelled earlier scenes."""
    from csa_core.adapt.continual import val_mious

    scored = [(inputs.target.id, scene)] if inputs.target.labelled else []
    for earlier in inputs.earlier:
        ctx.check()
        scored.append((earlier.id, load_scene(earlier, workdir, ground_truth=True, size=size)))
    mious = val_mious(net, [sc for _, sc in scored], device)
    return [Score(None, sid, _finite(miou)) for (sid, _), miou in zip(scored, mious, strict=True)]


def _save(
    inputs: AdaptInputs,
    workdir: Path,
    config: Any,
    state: Any,
    bank: StoredNerfMemory,
    net: Any,
    card: Any,
    record: dict[str, Any],
    scores: list[Score],
) -> AdaptOutputs:
    """Save the network and the BatchNorm memory; the outputs to register."""
    from csa_core.experiments.report import jsonable
    from csa_core.seg import save_checkpoint

    base, target = inputs.base, inputs.target
    mine = {score.scene_id: score.miou for score in scores if score.model_id is None}
    before = {score.scene_id: score.miou for score in scores if score.model_id == base.id}
    metrics = {
        "val_miou": mine.get(target.id),
        "before_val_miou": before.get(target.id),
        "pseudo_label_miou": _finite(record.get("pseudo_label_miou")),
        "prediction_miou": _finite(record.get("prediction_miou")),
        "trained": bool(record.get("trained", True)),
    }
    out = workdir / CHECKPOINT_FILE
    train_config = {
        "task": "adapt",
        "scene": target.name,
        "parent": base.name,
        "adapt": config.to_dict(),
    }
    save_checkpoint(out, net, card.child(train_config=train_config, metrics=metrics))
    batchnorm = None
    if state.batchnorm is not None:
        batchnorm = workdir / BATCHNORM_FILE
        state.batchnorm.save(batchnorm)
    quality = {
        "pseudo_label_miou": metrics["pseudo_label_miou"],
        "final_label_miou": _finite(record.get("final_label_miou")),
    }
    return AdaptOutputs(
        lineage=inputs.lineage,
        make_current=inputs.make_current,
        parent_id=base.id,
        parent_name=base.name,
        arch=base.arch,
        scene_id=target.id,
        checkpoint=out,
        batchnorm=batchnorm,
        nerf=bank.added[1] if bank.added is not None else None,
        nerf_preset=config.nerf.preset,
        nerf_quality=quality,
        metrics=metrics,
        meta={
            "task": "adapt",
            "preset": config.preset,
            "mode": config.mode,
            "step": jsonable(record),
        },
        scores=scores,
    )


def register(s: Session, outputs: AdaptOutputs, node: ApiNode) -> dict[str, Any]:
    n = len(s.scalars(select(ModelVersion.id).where(ModelVersion.lineage == outputs.lineage)).all())
    model = register_checkpoint(
        s,
        node.store,
        outputs.checkpoint,
        name=step_name(s, outputs.lineage, n),
        lineage=outputs.lineage,
        arch=outputs.arch,
        parent_id=outputs.parent_id,
        adapted_scene_id=outputs.scene_id,
        job_id=node.job_id,
        metrics=outputs.metrics,
        meta=outputs.meta,
        make_current=outputs.make_current,
        extra_files={BATCHNORM_FILE: outputs.batchnorm} if outputs.batchnorm is not None else {},
    )
    nerf_id = None
    if outputs.nerf is not None:
        labels_source = f"adapt:{outputs.parent_name}"
        nerf_id = add_nerf(
            s,
            node.store,
            outputs.scene_id,
            outputs.nerf,
            job_id=node.job_id,
            preset=outputs.nerf_preset,
            labels_source=labels_source,
            quality=outputs.nerf_quality,
        ).id
    for score in outputs.scores:
        model_id = model.id if score.model_id is None else score.model_id
        s.add(
            Evaluation(
                model_version_id=model_id,
                scene_id=score.scene_id,
                split="val",
                miou=score.miou,
                summary={},
                job_id=node.job_id,
            )
        )
    decisions = outputs.meta["step"].get("decisions", [])
    return {
        "model_id": model.id,
        "model": model.name,
        "parent_id": outputs.parent_id,
        "nerf_id": nerf_id,
        "metrics": outputs.metrics,
        "decisions": decisions,
    }
