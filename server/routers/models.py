"""``/api/v1/models``: the model registry (list with lineage and metrics, show, register,
set current, download; ``server/services/models.py``)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, File, Form, Query, Response, UploadFile, status
from fastapi.responses import FileResponse
from starlette.concurrency import run_in_threadpool

from server import capabilities
from server.auth import OperatorScope, PrincipalDep
from server.deps import DbDep, FormPartsChecked, ServicesDep, read_in_thread
from server.errors import not_available, too_large
from server.pagination import PAGE_RESPONSES, PageDep, page
from server.schemas.common import ERROR_RESPONSES, Name, ParamText
from server.schemas.models import ModelOut
from server.services import models

router = APIRouter(
    prefix="/models", tags=["models"], responses=ERROR_RESPONSES, dependencies=[OperatorScope]
)


@router.get("", response_model=list[ModelOut], responses=PAGE_RESPONSES)
def list_models(
    db: DbDep,
    response: Response,
    pages: PageDep,
    lineage: Annotated[Name | None, Query()] = None,
) -> list[ModelOut]:
    """Model versions (of ``lineage``) by id, a page at a time; ``X-Total-Count`` is the number
    of all of them."""
    rows = page(db, models.models_query(lineage), pages, response, models.ORDER)
    return [models.model_out(db, m) for m in rows]


@router.post(
    "",
    response_model=ModelOut,
    status_code=status.HTTP_201_CREATED,
    responses={409: ERROR_RESPONSES[422], 413: ERROR_RESPONSES[422], 501: ERROR_RESPONSES[422]},
    summary="register a segmentation checkpoint (safetensors with a CSA model card) as a new "
    "lineage root",
    dependencies=[FormPartsChecked],
)
async def register_model(
    db: DbDep,
    services: ServicesDep,
    principal: PrincipalDep,
    checkpoint: Annotated[
        UploadFile, File(description="CSA segmentation checkpoint (.safetensors)")
    ],
    name: Annotated[Name, Form()],
    lineage: Annotated[Name | None, Form(description="default: the model name")] = None,
    make_current: Annotated[
        bool | None, Form(description="default: when no model is current yet")
    ] = None,
) -> ModelOut:
    reason = capabilities.missing_reason("seg")
    if reason is not None:
        raise not_available(reason)
    lineage = lineage or name
    await read_in_thread(db, models.check_new_root, name, lineage)
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
            return models.register_upload(
                db,
                services.settings,
                services.store,
                principal,
                path,
                size,
                name=name,
                lineage=lineage,
                make_current=make_current,
            )
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    # Loading the weights and copying a file of up to a gigabyte into the store (hashed and
    # fsynced) take seconds: in a worker thread (which removes ``tmp``, so that a request given
    # up meanwhile cannot remove the file under it), and the event loop serves other requests.
    return await run_in_threadpool(check_and_register)


@router.get(
    "/{model_ref}", response_model=ModelOut, summary="a model version by id, name or 'current'"
)
def show_model(model_ref: ParamText, db: DbDep) -> ModelOut:
    return models.show_model(db, model_ref)


@router.post(
    "/{model_ref}/current",
    response_model=ModelOut,
    summary="make this version the one inference and new jobs use",
)
def make_current(model_ref: ParamText, db: DbDep) -> ModelOut:
    return models.make_current(db, model_ref)


@router.get(
    "/{model_ref}/download",
    response_class=FileResponse,
    responses={
        200: {
            "content": {"application/octet-stream": {}},
            "description": "the checkpoint (safetensors, model card in its header)",
        }
    },
)
def download_model(model_ref: ParamText, db: DbDep, services: ServicesDep) -> FileResponse:
    checkpoint = models.checkpoint_of(db, model_ref)
    sha = checkpoint.sha256
    return FileResponse(
        services.store.open_verified(sha),
        media_type="application/octet-stream",
        filename=f"{checkpoint.model_name}.safetensors",
        headers={"ETag": sha, "X-Checksum-Sha256": sha},
    )
