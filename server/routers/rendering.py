"""``/api/v1/scenes/{scene}/render``: colour, depth and labels from a scene's NeRF at any view
(the NeRF and the camera: ``server/services/nerfs.py``)."""

from __future__ import annotations

import base64

import cv2
import numpy as np
from fastapi import APIRouter, Request

from csa_core.data.image_files import depth_to_mm
from csa_core.data.label_images import colorize
from server import capabilities
from server.auth import OperatorScope
from server.deps import DbDep, ServicesDep, read_in_thread
from server.errors import not_available
from server.nerf_cache import NerfCache
from server.schemas.common import ERROR_RESPONSES, ErrorBody, ParamText
from server.schemas.rendering import RenderOut, RenderRequest
from server.services import nerfs

BUSY = {
    "model": ErrorBody,
    "description": "every render of this API process stayed busy for `CSA_RENDER_QUEUE_SECONDS` "
    '(code `render_busy`, `Retry-After` in seconds; docs/operations.md "Rendering")',
}
router = APIRouter(
    tags=["rendering"],
    responses={**ERROR_RESPONSES, 501: ERROR_RESPONSES[422], 503: BUSY},
    dependencies=[OperatorScope],
)


def _png(img: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return base64.b64encode(buf.tobytes()).decode("ascii")


@router.post(
    "/scenes/{scene_ref}/render",
    response_model=RenderOut,
    summary="render a view of the scene's NeRF",
)
async def render(
    scene_ref: ParamText, body: RenderRequest, request: Request, db: DbDep, services: ServicesDep
) -> RenderOut:
    reason = capabilities.missing_reason("nerf")
    if reason is not None:
        raise not_available(reason)
    pose = np.asarray(body.pose, dtype=np.float64)  # a rigid transform (schemas.common.Pose)
    camera = body.intrinsics.camera() if body.intrinsics is not None else None
    target = await read_in_thread(db, nerfs.render_target, scene_ref, body.nerf_id, camera)
    intr, nerf_id, files = target.camera, target.nerf.id, target.nerf.files
    cache: NerfCache = request.app.state.nerf_cache
    channels = list(dict.fromkeys(body.channels))

    def render_and_encode() -> dict[str, str]:
        view = cache.render_view(nerf_id, files, pose, intr)
        images: dict[str, str] = {}
        for channel in channels:
            if channel == "color":
                images[channel] = _png(cv2.cvtColor(view["color"], cv2.COLOR_RGB2BGR))
            elif channel == "depth":
                images[channel] = _png(depth_to_mm(view["depth"]))
            elif channel == "labels":
                images[channel] = _png(view["labels"].astype(np.uint8))
            else:
                images[channel] = _png(cv2.cvtColor(colorize(view["labels"]), cv2.COLOR_RGB2BGR))
        return images

    # The render and the PNG encoding, in a render thread when its turn comes (at most
    # CSA_RENDER_CONCURRENCY at once; 503 after CSA_RENDER_QUEUE_SECONDS of waiting): the
    # event loop serves other requests meanwhile (server/nerf_cache.py).
    images = await cache.run(render_and_encode)
    return RenderOut(
        scene_id=target.scene_id,
        nerf_id=nerf_id,
        width=intr.width,
        height=intr.height,
        images=images,
    )
