"""``adapt``: one step of the continual chain, delegated to ``csa_core.adapt.adapt_one_step``.

The job gathers the step's inputs from the service's stores and hands them to the core:
the lineage's newest network, the scene (its ground truth, when uploaded, is read only to
score), a replay buffer rendered from the memory-bank NeRFs of the scenes adapted to earlier
in the lineage, and the replay slice of the lineage root's pre-training scenes. It then
registers the outputs in one transaction: the new model version (parent = the version it
started from), the scene's NeRF in the memory bank, and the R-matrix entries this step makes
computable (the new version on every labelled scene of the lineage, the previous version
and the root on this scene).

Jobs of one lineage run one after another (the worker's lineage lock), so each step starts
from the version the previous step made.
"""

from __future__ import annotations

import math
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.db.models import Evaluation, Frame, Job, ModelVersion
from server.db.models import Scene as SceneRow
from server.errors import invalid
from server.jobs.context import JobContext
from server.jobs.inputs import load_scene, model_file, torch_device
from server.lookups import active_nerf, get_model, get_scene
from server.memory_bank import NERF_FILE, add_nerf
from server.registry import CHECKPOINT_FILE, lineage_chain, register_checkpoint
from server.schemas.jobs import AdaptParams


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
    normalized = {"scene_id": scene.id, "lineage": model.lineage, "preset": params.preset, "mode": params.mode, "make_current": params.make_current}
    return normalized, model.lineage


def _labelled(session: Session, scene_id: int) -> bool:
    rows = session.execute(select(Frame.labels_sha256).where(Frame.scene_id == scene_id)).all()
    return bool(rows) and all(sha is not None for (sha,) in rows)


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def run(ctx: JobContext) -> None:
    from csa_core.adapt import (
        MemoryBank,
        PretrainReplay,
        ReplayBuffer,
        adapt_one_step,
        label_entropy,
        preset,
    )
    from csa_core.data.scene import NYU40_FOLDER
    from csa_core.nerf.checkpoint import load_checkpoint as load_nerf
    from csa_core.nerf.checkpoint import save_checkpoint as save_nerf
    from csa_core.seg import ModelCard, evaluate_scene, load_checkpoint, save_checkpoint

    p = ctx.params
    device = torch_device(ctx)
    config = preset(p["preset"])
    if p.get("mode"):
        config.mode = p["mode"]
    config.seg.device = device

    with ctx.session() as s:
        chain = lineage_chain(s, p["lineage"])
        if not chain:
            raise LookupError(f"lineage {p['lineage']!r} has no model versions")
        root, base = chain[0], chain[-1]
        target = s.get(SceneRow, p["scene_id"])
        if target is None:
            raise LookupError(f"scene {p['scene_id']} no longer exists")
        target_name = target.name
        previous: list[tuple[int, str, dict[str, str]]] = []  # scenes adapted to earlier, oldest first
        for m in chain[1:]:
            sid = m.adapted_scene_id
            if sid is None or sid == p["scene_id"] or any(sid == q[0] for q in previous):
                continue
            nerf, row = active_nerf(s, sid), s.get(SceneRow, sid)
            if nerf is not None and row is not None:
                previous.append((sid, row.name, dict(nerf.files)))
        labelled = {sid: _labelled(s, sid) for sid in [p["scene_id"], *(q[0] for q in previous)]}
        pretrain_ids = [int(i) for i in (root.meta or {}).get("scene_ids", []) if s.get(SceneRow, int(i)) is not None]
        base_id, base_name, root_id, arch = base.id, base.name, root.id, base.arch

    ctx.progress(0.02, f"loading {base_name}", force=True)
    base_path, _ = model_file(ctx, base_id)
    net, card = load_checkpoint(base_path, device=device or "cpu")
    size = tuple(card.input_size) if card.input_size else None
    scene = load_scene(ctx, p["scene_id"], ground_truth=labelled[p["scene_id"]], size=size)

    ctx.progress(0.05, f"rendering the replay buffer from {len(previous)} earlier scene(s)", force=True)
    bank = MemoryBank(ctx.workdir / "memory")
    for _, name, files in previous:
        bank.add(name, load_nerf(ctx.store.open_verified(files[NERF_FILE]), device=device or "cpu"))
    replay = ReplayBuffer.from_memory_bank(bank, config.replay.buffer_size, config.replay.views, bank.scenes) if len(bank) else None
    pretrain_scenes = [load_scene(ctx, sid, ground_truth=True, size=size) for sid in pretrain_ids]
    pretrain = PretrainReplay.from_scenes(pretrain_scenes, config.replay.pretrain_fraction, config.replay.seed) if pretrain_scenes else None
    prior = label_entropy(f.labels[NYU40_FOLDER] for sc in pretrain_scenes for f in sc.train_frames if NYU40_FOLDER in f.labels) if pretrain_scenes else None

    scores: dict[tuple[int, int], float | None] = {}  # (model "base"/"root"/"new" key, scene id) -> val mIoU
    if labelled[p["scene_id"]]:
        ctx.progress(0.1, f"scoring {base_name} on {target_name} before adapting", force=True)
        scores[(base_id, p["scene_id"])] = _finite(evaluate_scene(net, scene, "val", device=device).miou())

    ctx.progress(0.15, f"adapting to {target_name} ({config.preset}, {config.mode})", force=True)
    step = adapt_one_step(net, scene, config, replay, pretrain, prior_entropy=prior, evaluate_before=False, on_progress=ctx.core_progress(0.15, 0.85))
    ctx.progress(0.85, "scoring the adapted network", force=True)

    new_key = -1  # the new version's id is known only once it is registered
    scores[(new_key, p["scene_id"])] = _finite(step.after.get("val")) if labelled[p["scene_id"]] else None
    for sid, _, _ in previous:
        if labelled[sid]:
            ctx.check()
            earlier = load_scene(ctx, sid, ground_truth=True, size=size)
            scores[(new_key, sid)] = _finite(evaluate_scene(net, earlier, "val", device=device).miou())
    if labelled[p["scene_id"]] and root_id != base_id:
        with ctx.session() as s:
            have_b = s.scalar(select(Evaluation.id).where(Evaluation.model_version_id == root_id, Evaluation.scene_id == p["scene_id"], Evaluation.split == "val").limit(1))
        if have_b is None:
            root_path, _ = model_file(ctx, root_id)
            root_net, _ = load_checkpoint(root_path, device=device or "cpu")
            scores[(root_id, p["scene_id"])] = _finite(evaluate_scene(root_net, scene, "val", device=device).miou())
            del root_net

    ctx.progress(0.95, "saving the network and the NeRF", force=True)
    out = ctx.workdir / CHECKPOINT_FILE
    step_record = step.to_dict()
    metrics = {
        "val_miou": scores.get((new_key, p["scene_id"])),
        "before_val_miou": scores.get((base_id, p["scene_id"])),
        "pseudo_label_miou": _finite(step.pseudo_label_miou),
        "prediction_miou": _finite(step.prediction_miou),
        "trained": step.trained,
    }
    save_checkpoint(out, net, ModelCard.for_model(net, input_size=card.input_size, train_config={"task": "adapt", "scene": target_name, "parent": base_name, "adapt": config.to_dict()}, metrics=metrics))
    nerf_out = None
    if step.nerf is not None:
        nerf_out = ctx.workdir / NERF_FILE
        save_nerf(step.nerf, nerf_out)

    def register(s: Session) -> dict[str, Any]:
        n = len(s.scalars(select(ModelVersion.id).where(ModelVersion.lineage == p["lineage"])).all())
        model = register_checkpoint(
            s,
            ctx.store,
            out,
            name=f"{p['lineage']}-step{n}",
            lineage=p["lineage"],
            arch=arch,
            parent_id=base_id,
            adapted_scene_id=p["scene_id"],
            job_id=ctx.job_id,
            metrics=metrics,
            meta={"task": "adapt", "preset": config.preset, "mode": config.mode, "step": step_record},
            make_current=p["make_current"],
        )
        nerf_id = None
        if nerf_out is not None:
            quality = {"pseudo_label_miou": metrics["pseudo_label_miou"], "final_label_miou": _finite(step.final_label_miou)}
            nerf_id = add_nerf(s, ctx.store, p["scene_id"], nerf_out, job_id=ctx.job_id, preset=config.nerf.preset, labels_source=f"adapt:{base_name}", quality=quality).id
        for (model_key, sid), miou in scores.items():
            s.add(Evaluation(model_version_id=model.id if model_key == new_key else model_key, scene_id=sid, split="val", miou=miou, summary={}, job_id=ctx.job_id))
        return {"model_id": model.id, "model": model.name, "parent_id": base_id, "nerf_id": nerf_id, "metrics": metrics, "decisions": step_record.get("decisions", [])}

    ctx.complete(register)
