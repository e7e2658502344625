"""``/api/v1/predict``: an image in, a NYU40 label map out (PNG), from any model version
(``server/services/models.py`` names its checkpoint)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, File, Form, Request, UploadFile
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from csa_core.data import image_files
from csa_core.data.label_images import colorize
from csa_core.errors import CSAInputError
from server import capabilities
from server.auth import DeviceScope
from server.deps import DbDep, FormPartsChecked, ServicesDep, read_in_thread
from server.errors import invalid, not_available, too_large
from server.image_headers import UploadHeaderError, check_upload_header
from server.schemas.common import ERROR_RESPONSES
from server.services import models

router = APIRouter(
    tags=["inference"],
    responses={**ERROR_RESPONSES, 413: ERROR_RESPONSES[422], 501: ERROR_RESPONSES[422]},
    dependencies=[DeviceScope],
)


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


@router.post(
    "/predict",
    response_class=Response,
    responses={
        200: {
            "content": {"image/png": {}},
            "description": "uint8 NYU40 ids (format=ids) or the palette picture (format=color)",
        }
    },
    summary="label an RGB image with the current or a named model version",
    dependencies=[FormPartsChecked],
)
async def predict(
    request: Request,
    db: DbDep,
    services: ServicesDep,
    image: Annotated[UploadFile, File(description="8-bit RGB image, PNG or JPEG")],
    model: Annotated[
        str | None, Form(max_length=128, description="model version id or name (default: current)")
    ] = None,
    format: Annotated[Literal["ids", "color"], Form()] = "ids",
) -> Response:
    reason = capabilities.missing_reason("seg")
    if reason is not None:
        raise not_available(reason)
    limit = services.settings.max_inference_upload_bytes
    data = await image.read(limit + 1)
    if len(data) > limit:
        raise too_large("image", limit)
    checkpoint = await read_in_thread(db, models.checkpoint_of, model)
    sha, name, version_id = checkpoint.sha256, checkpoint.model_name, checkpoint.model_id
    max_pixels = services.settings.max_image_pixels
    model_cache = request.app.state.model_cache

    def label() -> bytes:
        try:  # the JPEG check walks the whole file: off the event loop
            fmt = check_upload_header(data, "image", max_pixels).fmt
        except UploadHeaderError as e:
            raise invalid(e.where, e.problem) from None
        with tempfile.TemporaryDirectory(prefix="csa-predict-") as d:
            path = Path(d) / f"image{fmt}"
            path.write_bytes(data)
            try:
                rgb = image_files.read_color(path)
            except CSAInputError as e:
                raise invalid("image", e.problem) from None
        labels = model_cache.predict(sha, rgb)
        return (
            _png(labels.astype(np.uint8))
            if format == "ids"
            else _png(cv2.cvtColor(colorize(labels), cv2.COLOR_RGB2BGR))
        )

    # Decoding, the network and encoding the answer take a while: in a worker thread, so that
    # the event loop keeps serving every other request meanwhile.
    body = await run_in_threadpool(label)
    return Response(
        body,
        media_type="image/png",
        headers={"X-CSA-Model-Id": str(version_id), "X-CSA-Model": name},
    )
