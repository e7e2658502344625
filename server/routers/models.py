"""``/api/v1/models``: the model registry (list with lineage and metrics, show, register,
set current, download)."""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Query, Response, UploadFile, status
from fastapi.responses import FileResponse
from sqlalchemy import Select, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from csa_core.data.camera import parse_size
from csa_core.errors import CSAInputError
from server import capabilities
from server.auth import OperatorScope, PrincipalDep
from server.db.models import Evaluation, ModelVersion, Scene
from server.deps import DbDep, FormPartsChecked, ServicesDep
from server.errors import conflict, invalid, not_available, too_large
from server.lookups import get_model
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.quotas import UPLOADER_META, account_of_principal, check_stored_bytes
from server.registry import checkpoint_sha, register_checkpoint, root_conflict, set_current
from server.schemas.common import ERROR_RESPONSES, Name
from server.schemas.models import ModelOut

router = APIRouter(prefix="/models", tags=["models"], responses=ERROR_RESPONSES, dependencies=[OperatorScope])


def model_out(db: Session, m: ModelVersion) -> ModelOut:
    children = list(db.scalars(select(ModelVersion.id).where(ModelVersion.parent_id == m.id).order_by(ModelVersion.id)))
    scene_name = db.scalar(select(Scene.name).where(Scene.id == m.adapted_scene_id)) if m.adapted_scene_id else None
    evals: dict[str, float | None] = {}
    for ev, name in db.execute(select(Evaluation, Scene.name).join(Scene, Scene.id == Evaluation.scene_id).where(Evaluation.model_version_id == m.id).order_by(Evaluation.id)):
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
    q = select(ModelVersion).order_by(ModelVersion.id)
    if lineage is not None:
        q = q.where(ModelVersion.lineage == lineage)
    return q


def all_models(db: Session, lineage: str | None = None) -> list[ModelOut]:
    """Every model version (of ``lineage``), by id: for the dashboard, which shows them all."""
    return [model_out(db, m) for m in db.scalars(models_query(lineage))]


@router.get("", response_model=list[ModelOut], responses=PAGE_RESPONSES)
def list_models(
    db: DbDep,
    response: Response,
    pages: PageDep,
    lineage: Annotated[Name | None, Query()] = None,
) -> list[ModelOut]:
    """Model versions (of ``lineage``) by id, a page at a time; ``X-Total-Count`` is the number
    of all of them."""
    return [model_out(db, m) for m in page(db, models_query(lineage), pages, response, (ModelVersion.id,))]


def _non_finite_number(value: Any, where: str) -> str | None:
    """Where a NaN or an infinity sits in parsed JSON (``metrics.miou``), or None. The card's
    metrics are stored with the version (the database's JSON holds no such numbers: PostgreSQL
    refuses them, SQLite keeps text that is not JSON) and sent in every listing of the models."""
    todo = [(value, where)]
    while todo:
        item, at = todo.pop()
        if isinstance(item, float) and not math.isfinite(item):
            return at
        if isinstance(item, dict):
            todo.extend((v, f"{at}.{k}") for k, v in item.items())
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
                raise CSAInputError("checkpoint", f"model card input_size: {e.problem}") from None
            if w * h > max_pixels:
                raise CSAInputError("checkpoint", f"model card input_size: {w}x{h} is more than the limit of {max_pixels} pixels")
        where = _non_finite_number(card.metrics, "metrics")
        if where is not None:
            raise CSAInputError("checkpoint", f"model card {where} is not a finite number (NaN and infinities cannot be stored)")
        load_checkpoint(path, device="cpu")
    except CSAInputError as e:
        raise invalid("checkpoint", e.problem) from None
    return card


@router.post(
    "",
    response_model=ModelOut,
    status_code=status.HTTP_201_CREATED,
    responses={409: ERROR_RESPONSES[422], 413: ERROR_RESPONSES[422], 501: ERROR_RESPONSES[422]},
    summary="register a segmentation checkpoint (safetensors with a CSA model card) as a new lineage root",
    dependencies=[FormPartsChecked],
)
async def register_model(
    db: DbDep,
    services: ServicesDep,
    principal: PrincipalDep,
    checkpoint: Annotated[UploadFile, File(description="CSA segmentation checkpoint (.safetensors)")],
    name: Annotated[Name, Form()],
    lineage: Annotated[Name | None, Form(description="default: the model name")] = None,
    make_current: Annotated[bool | None, Form(description="default: when no model is current yet")] = None,
) -> ModelOut:
    reason = capabilities.missing_reason("seg")
    if reason is not None:
        raise not_available(reason)
    lineage = lineage or name
    taken = root_conflict(db, name, lineage, "an uploaded checkpoint")
    if taken is not None:
        raise conflict(taken[1], field=taken[0])
    limit = services.settings.max_model_upload_bytes
    tmp = Path(tempfile.mkdtemp(prefix="csa-model-", dir=services.settings.resolved_work_dir))
    try:
        path = tmp / "model.safetensors"
        size = 0
        with open(path, "wb") as out:
            while chunk := await checkpoint.read(1 << 20):
                size += len(chunk)
                if size > limit:
                    raise too_large("checkpoint", limit)
                out.write(chunk)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

    def check_and_register() -> ModelOut:
        try:
            account = account_of_principal(principal)
            check_stored_bytes(db, services.settings, account, size, "checkpoint")  # before storing
            card = _checked_card(path, services.settings.max_image_pixels)
            meta = {"task": "upload", "card_created": card.created}
            if principal.key_id is not None:
                meta[UPLOADER_META] = principal.key_id  # counted in the key's stored bytes
            model = register_checkpoint(
                db, services.store, path, name=name, lineage=lineage, arch=card.arch, metrics=dict(card.metrics or {}), meta=meta, make_current=make_current
            )
            try:
                db.commit()
            except IntegrityError:  # the same name registered by a concurrent request
                db.rollback()
                raise conflict(f"a model version named {name!r} exists", field="name") from None
            return model_out(db, model)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    # Loading the weights and copying a file of up to a gigabyte into the store (hashed and
    # fsynced) take seconds: in a worker thread (which removes ``tmp``, so that a request given
    # up meanwhile cannot remove the file under it), and the event loop serves other requests.
    return await run_in_threadpool(check_and_register)


@router.get("/{model_ref}", response_model=ModelOut, summary="a model version by id, name or 'current'")
def show_model(model_ref: str, db: DbDep) -> ModelOut:
    return model_out(db, get_model(db, model_ref))


@router.post("/{model_ref}/current", response_model=ModelOut, summary="make this version the one inference and new jobs use")
def make_current(model_ref: str, db: DbDep) -> ModelOut:
    model = get_model(db, model_ref)
    set_current(db, model)
    db.commit()
    return model_out(db, model)


@router.get(
    "/{model_ref}/download",
    response_class=FileResponse,
    responses={200: {"content": {"application/octet-stream": {}}, "description": "the checkpoint (safetensors, model card in its header)"}},
)
def download_model(model_ref: str, db: DbDep, services: ServicesDep) -> FileResponse:
    model = get_model(db, model_ref)
    sha = checkpoint_sha(model)
    return FileResponse(services.store.open_verified(sha), media_type="application/octet-stream", filename=f"{model.name}.safetensors", headers={"ETag": sha, "X-Checksum-Sha256": sha})
