"""``adapt``: one step of the continual chain, the core's ``csa_core.adapt.step.continual_step``.

The job loads the step's inputs from the service's stores: the lineage's newest network and
its BatchNorm memory (a file of that version), the scene (its ground truth, when uploaded, is
read only to score), the NeRFs the lineage's earlier steps banked (read from the artifact
store as stored, :class:`server.memory_bank.StoredNerfMemory`), and the lineage root's
pre-training scenes. It builds the core's :class:`~csa_core.adapt.step.ContinualState` from
them and takes the one step that ``csa adapt`` and ``csa experiment`` take, so the same
inputs, seed and thread count give the same network on a CPU (on CUDA, atomic additions in the
hash grid's backward pass and cuDNN make two runs agree only statistically). It then registers the outputs in one
transaction: the new model version (parent = the version it started from) with the BatchNorm
memory after the step, the scene's NeRF in the memory bank (unless the collapse guard skipped
the scene), and the R-matrix entries this step makes computable (the new version on every
labelled scene of the lineage, the previous version and the root on this scene), scored by
the core's ``csa_core.adapt.continual.val_mious``.

Jobs of one lineage run one after another (the worker's lineage lock), so each step starts
from the version the previous step made.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db.models import Evaluation, Frame, Job, ModelVersion
from server.db.models import Scene as SceneRow
from server.errors import invalid
from server.jobs.context import JobContext
from server.jobs.inputs import load_scene, model_file, torch_device, version_file
from server.lookups import get_model, get_scene
from server.memory_bank import StoredNerfMemory, add_nerf, lineage_nerfs
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
    normalized = {"scene_id": scene.id, "lineage": model.lineage, "preset": params.preset, "mode": params.mode, "seed": params.seed, "make_current": params.make_current}
    return normalized, model.lineage


def _labelled(session: Session, scene_id: int) -> bool:
    rows = session.execute(select(Frame.labels_sha256).where(Frame.scene_id == scene_id)).all()
    return bool(rows) and all(sha is not None for (sha,) in rows)


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


def run(ctx: JobContext) -> None:
    from csa_core.adapt import preset
    from csa_core.adapt.bn_memory import BatchNormMemory
    from csa_core.adapt.continual import val_mious
    from csa_core.adapt.step import ContinualState, continual_step
    from csa_core.experiments.inputs import seeded
    from csa_core.experiments.report import jsonable
    from csa_core.seg import load_checkpoint, save_checkpoint

    p = ctx.params
    device = torch_device(ctx)
    config = seeded(preset(p["preset"]), p.get("seed", 0))
    if p.get("mode"):
        config.mode = p["mode"]
    config.seg.device = device
    target_id = p["scene_id"]

    with ctx.session() as s:
        chain = lineage_chain(s, p["lineage"])
        if not chain:
            raise LookupError(f"lineage {p['lineage']!r} has no model versions")
        root, base = chain[0], chain[-1]
        target = s.get(SceneRow, target_id)
        if target is None:
            raise LookupError(f"scene {target_id} no longer exists")
        target_name = target.name
        earlier: list[int] = []  # scenes adapted to earlier in the lineage, oldest first
        for m in chain[1:]:
            sid = m.adapted_scene_id
            if sid is not None and sid != target_id and sid not in earlier and s.get(SceneRow, sid) is not None:
                earlier.append(sid)
        nerfs = lineage_nerfs(s, chain[1:], exclude_scene_id=target_id)
        labelled = {sid: _labelled(s, sid) for sid in [target_id, *earlier]}
        pretrain_ids = [int(i) for i in (root.meta or {}).get("scene_ids", []) if s.get(SceneRow, int(i)) is not None]
        base_id, base_name, root_id, arch = base.id, base.name, root.id, base.arch
        has_batchnorm = BATCHNORM_FILE in (base.files or {})

    ctx.progress(0.02, f"loading {base_name}", force=True)
    base_path, _ = model_file(ctx, base_id)
    net, card = load_checkpoint(base_path, device=device or "cpu")
    size = tuple(card.input_size) if card.input_size else None
    scene = load_scene(ctx, target_id, ground_truth=labelled[target_id], size=size)
    pretrain_scenes = [load_scene(ctx, sid, ground_truth=True, size=size) for sid in pretrain_ids]
    batchnorm = BatchNormMemory.load(version_file(ctx, base_id, BATCHNORM_FILE)) if has_batchnorm else None
    bank = StoredNerfMemory(ctx.store, nerfs, ctx.workdir / "memory")
    state = ContinualState.start(config, "ours", bank=bank, pretrain_scenes=pretrain_scenes, batchnorm=batchnorm)

    scores: dict[tuple[int, int], float | None] = {}  # (model version id, scene id) -> val mIoU
    if labelled[target_id]:
        ctx.progress(0.1, f"scoring {base_name} on {target_name} before adapting", force=True)
        scores[(base_id, target_id)] = _finite(val_mious(net, [scene], device)[0])

    ctx.progress(0.15, f"adapting to {target_name} ({config.preset}, {config.mode}; {len(nerfs)} earlier scene(s) to replay)", force=True)
    record = continual_step(state, net, scene, on_progress=ctx.core_progress(0.15, 0.85))
    ctx.progress(0.85, "scoring the adapted network", force=True)

    new_key = -1  # the new version's id is known only once it is registered
    scored = [(target_id, scene)] if labelled[target_id] else []
    for sid in earlier:
        if labelled[sid]:
            ctx.check()
            scored.append((sid, load_scene(ctx, sid, ground_truth=True, size=size)))
    for (sid, _), miou in zip(scored, val_mious(net, [sc for _, sc in scored], device), strict=True):
        scores[(new_key, sid)] = _finite(miou)
    if labelled[target_id] and root_id != base_id:
        with ctx.session() as s:
            have_b = s.scalar(select(Evaluation.id).where(Evaluation.model_version_id == root_id, Evaluation.scene_id == target_id, Evaluation.split == "val").limit(1))
        if have_b is None:
            root_path, _ = model_file(ctx, root_id)
            root_net, _ = load_checkpoint(root_path, device=device or "cpu")
            scores[(root_id, target_id)] = _finite(val_mious(root_net, [scene], device)[0])
            del root_net

    ctx.progress(0.95, "saving the network, its BatchNorm memory and the NeRF", force=True)
    out = ctx.workdir / CHECKPOINT_FILE
    metrics = {
        "val_miou": scores.get((new_key, target_id)),
        "before_val_miou": scores.get((base_id, target_id)),
        "pseudo_label_miou": _finite(record.get("pseudo_label_miou")),
        "prediction_miou": _finite(record.get("prediction_miou")),
        "trained": bool(record.get("trained", True)),
    }
    train_config = {"task": "adapt", "scene": target_name, "parent": base_name, "adapt": config.to_dict()}
    save_checkpoint(out, net, card.child(train_config=train_config, metrics=metrics))
    extra_files = {}
    if state.batchnorm is not None:
        extra_files[BATCHNORM_FILE] = ctx.workdir / BATCHNORM_FILE
        state.batchnorm.save(extra_files[BATCHNORM_FILE])
    step_record = jsonable(record)

    def register(s: Session) -> dict[str, Any]:
        n = len(s.scalars(select(ModelVersion.id).where(ModelVersion.lineage == p["lineage"])).all())
        model = register_checkpoint(
            s,
            ctx.store,
            out,
            name=step_name(s, p["lineage"], n),
            lineage=p["lineage"],
            arch=arch,
            parent_id=base_id,
            adapted_scene_id=target_id,
            job_id=ctx.job_id,
            metrics=metrics,
            meta={"task": "adapt", "preset": config.preset, "mode": config.mode, "step": step_record},
            make_current=p["make_current"],
            extra_files=extra_files,
        )
        nerf_id = None
        if bank.added is not None:
            quality = {"pseudo_label_miou": metrics["pseudo_label_miou"], "final_label_miou": _finite(record.get("final_label_miou"))}
            nerf_id = add_nerf(s, ctx.store, target_id, bank.added[1], job_id=ctx.job_id, preset=config.nerf.preset, labels_source=f"adapt:{base_name}", quality=quality).id
        for (model_key, sid), miou in scores.items():
            s.add(Evaluation(model_version_id=model.id if model_key == new_key else model_key, scene_id=sid, split="val", miou=miou, summary={}, job_id=ctx.job_id))
        return {"model_id": model.id, "model": model.name, "parent_id": base_id, "nerf_id": nerf_id, "metrics": metrics, "decisions": step_record.get("decisions", [])}

    ctx.complete(register)
