"""Model versions: the registry's listing with lineage and metrics, uploads of checkpoints as
new lineage roots, the current version, and the checkpoint files (``/api/v1/models``,
``/api/v1/predict``, the dashboard's model pages). Storing a checkpoint as a version is
``server/registry.py``'s, shared with the jobs that make versions."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import Select, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from csa_core.data.camera import parse_size
from csa_core.errors import CSAInputError
from server.artifacts import ArtifactStore
from server.db.models import Evaluation, ModelVersion, Scene
from server.errors import conflict, invalid, is_utf8_text
from server.keys import Principal
from server.lookups import current_model, get_model
from server.quotas import UPLOADER_META, account_of_principal, check_stored_bytes
from server.registry import checkpoint_sha, register_checkpoint, root_conflict, set_current
from server.schemas.models import ModelOut
from server.settings import Settings

ORDER = (ModelVersion.id,)  # the sort key of :func:`models_query` (server/pagination.py)


def model_out(db: Session, m: ModelVersion) -> ModelOut:
    children = list(
        db.scalars(
            select(ModelVersion.id).where(ModelVersion.parent_id == m.id).order_by(ModelVersion.id)
        )
    )
    scene_name = (
        db.scalar(select(Scene.name).where(Scene.id == m.adapted_scene_id))
        if m.adapted_scene_id
        else None
    )
    evals: dict[str, float | None] = {}
    scored = (
        select(Evaluation, Scene.name)
        .join(Scene, Scene.id == Evaluation.scene_id)
        .where(Evaluation.model_version_id == m.id)
        .order_by(Evaluation.id)
    )
    for ev, name in db.execute(scored):
        evals[f"{name}/{ev.split}"] = ev.miou
    return ModelOut(
        id=m.id,
        name=m.name,
        lineage=m.lineage,
        parent_id=m.parent_id,
        children=children,
        adapted_scene_id=m.adapted_scene_id,
        adapted_scene=scene_name,
        job_id=m.job_id,
        arch=m.arch,
        size_bytes=m.size_bytes,
        sha256=checkpoint_sha(m),
        metrics=m.metrics or {},
        evaluations=evals,
        is_current=m.is_current,
        created_at=m.created_at,
    )


def models_query(lineage: str | None = None) -> Select:
    q = select(ModelVersion).order_by(*ORDER)
    if lineage is not None:
        q = q.where(ModelVersion.lineage == lineage)
    return q


def all_models(db: Session, lineage: str | None = None) -> list[ModelOut]:
    """Every model version (of ``lineage``), by id: for the dashboard, which shows them all."""
    return [model_out(db, m) for m in db.scalars(models_query(lineage))]


def show_model(db: Session, model_ref: str) -> ModelOut:
    """A version by id, name or ``current``; 404 otherwise."""
    return model_out(db, get_model(db, model_ref))


def current_model_out(db: Session) -> ModelOut | None:
    """The current version, or None when there is none yet."""
    model = current_model(db)
    return model_out(db, model) if model is not None else None


def make_current(db: Session, model_ref: str) -> ModelOut:
    """Make a version the one inference and new jobs use."""
    model = get_model(db, model_ref)
    set_current(db, model)
    db.commit()
    return model_out(db, model)


@dataclass(frozen=True)
class Checkpoint:
    """A version's checkpoint file: its checksum in the artifact store, and the version."""

    sha256: str
    model_id: int
    model_name: str


def checkpoint_of(db: Session, model_ref: str | None) -> Checkpoint:
    """The checkpoint of a version by id or name, or of the current one (``None`` or
    ``current``); 404 otherwise."""
    model = get_model(db, model_ref)
    return Checkpoint(checkpoint_sha(model), model.id, model.name)


def current_checkpoint(db: Session) -> Checkpoint | None:
    """The current version's checkpoint, or None when no version is current."""
    model = current_model(db)
    return Checkpoint(checkpoint_sha(model), model.id, model.name) if model is not None else None


# -- uploads ---------------------------------------------------------------------------------


def check_new_root(db: Session, name: str, lineage: str) -> None:
    """Before an upload is read: 409 when ``name`` or ``lineage`` is taken (or will be, by a
    pre-training under way), since an uploaded checkpoint starts a new lineage."""
    taken = root_conflict(db, name, lineage, "an uploaded checkpoint")
    if taken is not None:
        raise conflict(taken[1], field=taken[0])


def _unstorable(value: Any, where: str) -> str | None:
    """What makes ``value`` (parsed JSON, found at ``where``) unfit to store and answer, naming
    where it sits (``metrics.miou is not a finite number ...``), or None. The card's metrics are
    stored with the version and sent in every listing of the models: the database's JSON holds
    no NaN or infinity (PostgreSQL refuses them, SQLite keeps text that is not JSON), and no
    answer can encode a lone surrogate (JSON's ``"\\ud800"``), in a value or a key."""
    todo = [(value, where)]
    while todo:
        item, at = todo.pop()
        if isinstance(item, float) and not math.isfinite(item):
            return f"{at} is not a finite number (NaN and infinities cannot be stored)"
        if isinstance(item, str) and not is_utf8_text(item):
            return f"{at} is not Unicode text (it holds a lone surrogate)"
        if isinstance(item, dict):
            for k, v in item.items():
                if not is_utf8_text(k):
                    return f"{at} has a key that is not Unicode text (it holds a lone surrogate)"
                todo.append((v, f"{at}.{k}"))
        elif isinstance(item, list):
            todo.extend((v, f"{at}[{i}]") for i, v in enumerate(item))
    return None


def _checked_card(path: Path, max_pixels: int):
    """The model card of an uploaded checkpoint, once the whole file has been checked: the card
    (``csa_core.seg.checkpoint``), its input size (inference and jobs run the network at it, so
    it may not exceed the pixels of an image the service accepts), and weights that load into
    the card's network on the CPU, so that nothing registered can fail later at inference or in
    a job; 422 otherwise."""
    from csa_core.seg import load_checkpoint, read_model_card

    try:
        card = read_model_card(path)
        size = card.input_size
        if size is not None:
            try:
                w, h = parse_size(f"{size[0]}x{size[1]}", "checkpoint")
            except CSAInputError as e:
                problem = f"model card input_size: {e.problem}"
                raise CSAInputError("checkpoint", problem) from None
            if w * h > max_pixels:
                problem = (
                    f"model card input_size: {w}x{h} is more than the limit of {max_pixels} pixels"
                )
                raise CSAInputError("checkpoint", problem)
        problem = _unstorable(card.metrics, "metrics")
        if problem is not None:
            raise CSAInputError("checkpoint", f"model card {problem}")
        load_checkpoint(path, device="cpu")
    except CSAInputError as e:
        raise invalid("checkpoint", e.problem) from None
    return card


def register_upload(
    db: Session,
    settings: Settings,
    store: ArtifactStore,
    principal: Principal,
    path: Path,
    size: int,
    *,
    name: str,
    lineage: str,
    make_current: bool | None,
) -> ModelOut:
    """Register an uploaded checkpoint (``size`` bytes at ``path``) as the root of a new
    lineage, once the stored-bytes quota of the key that sent it and the checkpoint itself are
    checked; slow (loading the weights, copying the file into the store): callers run it off
    the event loop."""
    account = account_of_principal(principal)
    check_stored_bytes(db, settings, account, size, "checkpoint")  # before storing
    card = _checked_card(path, settings.max_image_pixels)
    meta = {"task": "upload", "card_created": card.created}
    if principal.key_id is not None:
        meta[UPLOADER_META] = principal.key_id  # counted in the key's stored bytes
    model = register_checkpoint(
        db,
        store,
        path,
        name=name,
        lineage=lineage,
        arch=card.arch,
        metrics=dict(card.metrics or {}),
        meta=meta,
        make_current=make_current,
    )
    try:
        db.commit()
    except IntegrityError:  # the same name registered by a concurrent request
        db.rollback()
        raise conflict(f"a model version named {name!r} exists", field="name") from None
    return model_out(db, model)
