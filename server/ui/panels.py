"""Pictures of a stored frame for the dashboard: the network's labels, the NeRF's rendered
pseudo-labels, ground truth, and an overlay, as PNG.

Predictions go through the service's model cache (as ``/api/v1/predict`` does) and renders
through its NeRF cache (as ``/api/v1/scenes/{scene}/render`` does); colours, overlays and
the legend are ``csa_core.data.label_images``'.
"""

from __future__ import annotations

import base64
import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from sqlalchemy.orm import Session

from csa_core.data import image_files
from csa_core.data.camera import Intrinsics
from csa_core.data.label_images import colorize, overlay
from csa_core.data.nyu40 import CLASS_NAMES, PALETTE
from server import capabilities
from server.artifacts import ArtifactStore
from server.db.models import Frame, Scene
from server.errors import invalid, not_available, not_found
from server.image_headers import UploadHeaderError, check_upload_header
from server.model_cache import ModelCache
from server.nerf_cache import NerfCache
from server.services.models import checkpoint_of
from server.services.nerfs import MAX_RENDER_PIXELS, active_nerf_files

Panel = Literal["prediction", "pseudo", "truth", "overlay"]
PANELS: tuple[str, ...] = ("prediction", "pseudo", "truth", "overlay")


def png(rgb_or_ids: np.ndarray) -> bytes:
    """PNG bytes of an RGB (H, W, 3) or single-channel image."""
    img = cv2.cvtColor(rgb_or_ids, cv2.COLOR_RGB2BGR) if rgb_or_ids.ndim == 3 else rgb_or_ids
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def b64png(image: np.ndarray) -> str:
    return base64.b64encode(png(image)).decode("ascii")


@dataclass(frozen=True)
class PanelSource:
    """What a panel is computed from, read while the request's session is open; ``etag``
    changes whenever the picture would (other frame, model or NeRF)."""

    panel: str
    color_sha: str
    labels_sha: str | None
    model_sha: str | None
    nerf_id: int | None
    nerf_files: dict[str, str] | None
    pose: list[list[float]] | None
    intrinsics: dict[str, float] | None

    @property
    def labels_key(self) -> tuple[object, ...]:
        """What the label map depends on (the frame's image, and the model or the NeRF and pose)."""
        pose = tuple(v for row in self.pose for v in row) if self.pose is not None else None
        return (self.color_sha, self.labels_sha, self.model_sha, self.nerf_id, pose)

    @property
    def etag(self) -> str:
        key = repr((self.panel, *self.labels_key))
        return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


class LabelMaps:
    """The label maps of the frames drawn lately: a frame's labels and their overlay, which a
    page asks for at the same moment, cost one prediction or one render."""

    def __init__(self, size: int = 32):
        self.size = size
        self._items: OrderedDict[tuple[object, ...], Future[np.ndarray]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple[object, ...], make: Callable[[], np.ndarray]) -> np.ndarray:
        with self._lock:
            future = self._items.get(key)
            mine = future is None
            if future is None:
                future = self._items[key] = Future()
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        if mine:
            try:
                future.set_result(make())
            except BaseException as e:
                future.set_exception(e)
                with self._lock:
                    if self._items.get(key) is future:
                        del self._items[key]
        return future.result()


def panel_source(db: Session, scene: Scene, frame: Frame, panel: str) -> PanelSource:
    """Resolve what ``panel`` needs, or answer why it cannot be drawn (404 / 501)."""
    nerf = active_nerf_files(db, scene.id) if panel in ("pseudo", "overlay") else None
    model_sha = None
    if panel == "prediction" or (panel == "overlay" and nerf is None):
        reason = capabilities.missing_reason("seg")
        if reason is not None:
            raise not_available(reason)
        model_sha = checkpoint_of(db, None).sha256
    if panel == "pseudo":
        reason = capabilities.missing_reason("nerf")
        if reason is not None:
            raise not_available(reason)
        if nerf is None:
            raise not_found("NeRF of scene", scene.name)
    if panel == "truth" and frame.labels_sha256 is None:
        raise not_found("labels of frame", frame.name)
    return PanelSource(
        panel=panel,
        color_sha=frame.color_sha256,
        labels_sha=frame.labels_sha256 if panel == "truth" else None,
        model_sha=model_sha,
        nerf_id=nerf.id if nerf is not None else None,
        nerf_files=nerf.files if nerf is not None else None,
        pose=frame.pose if nerf is not None else None,
        intrinsics=dict(scene.intrinsics) if scene.intrinsics else None,
    )


def render_camera(intr: Intrinsics) -> Intrinsics:
    """The camera a frame's pseudo-labels are rendered at: the frame's, scaled down (same
    aspect ratio) to at most the render route's :data:`MAX_RENDER_PIXELS`, since a view holds
    class scores for every pixel; the labels are then resized to the frame."""
    pixels = intr.width * intr.height
    if pixels <= MAX_RENDER_PIXELS:
        return intr
    s = math.sqrt(MAX_RENDER_PIXELS / pixels)
    return intr.scaled(max(1, int(intr.width * s)), max(1, int(intr.height * s)))


def draw_panel(
    src: PanelSource, store: ArtifactStore, models: ModelCache, nerfs: NerfCache, maps: LabelMaps
) -> bytes:
    """The panel as PNG: NYU40 colours, or for ``overlay`` the colours blended into the image
    (the NeRF's pseudo-labels when the scene has a NeRF, else the network's prediction)."""
    if src.panel == "truth":
        assert src.labels_sha is not None
        return png(colorize(image_files.read_label_image(store.open_verified(src.labels_sha))))
    color = image_files.read_color(store.open_verified(src.color_sha))

    def labels_of_frame() -> np.ndarray:
        if src.nerf_id is not None:
            assert src.nerf_files and src.pose is not None and src.intrinsics is not None
            pose = np.asarray(src.pose, dtype=np.float64)
            camera = render_camera(Intrinsics.from_dict(src.intrinsics))
            view = nerfs.render(src.nerf_id, src.nerf_files, pose, camera)
            labels = view["labels"].astype(np.uint8)
        else:
            assert src.model_sha is not None
            labels = models.predict(src.model_sha, color)
        if labels.shape != color.shape[:2]:
            size = (color.shape[1], color.shape[0])
            labels = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
        return labels

    labels = maps.get(src.labels_key, labels_of_frame)
    return png(overlay(color, labels) if src.panel == "overlay" else colorize(labels))


def class_color(class_id: int) -> str:
    """The NYU40 colour of a class as ``#rrggbb`` (the pictures' colours)."""
    return "#{:02x}{:02x}{:02x}".format(*(int(v) for v in PALETTE[class_id]))


def class_legend() -> list[dict[str, object]]:
    """Every NYU40 class with its colour, in id order: the legend of the scene page's pictures."""
    return [{"id": i, "name": name, "color": class_color(i)} for i, name in enumerate(CLASS_NAMES)]


def legend(labels: np.ndarray) -> list[dict[str, object]]:
    """The classes in a label map, most frequent first: id, name, colour and pixel share."""
    ids, counts = np.unique(labels, return_counts=True)
    order = np.argsort(-counts, kind="stable")
    total = int(labels.size)
    return [
        {
            "id": int(ids[i]),
            "name": CLASS_NAMES[int(ids[i])],
            "color": class_color(int(ids[i])),
            "share": int(counts[i]) / total,
        }
        for i in order
    ]


def predict_preview(
    db: Session, models: ModelCache, data: bytes, max_pixels: int
) -> dict[str, object]:
    """Label an uploaded image with the current model: overlay, colours and legend."""
    reason = capabilities.missing_reason("seg")
    if reason is not None:
        raise not_available(reason)
    checkpoint = checkpoint_of(db, None)
    sha, name, model_id = checkpoint.sha256, checkpoint.model_name, checkpoint.model_id
    db.close()
    try:
        check_upload_header(data, "image", max_pixels)
    except UploadHeaderError as e:
        raise invalid(e.where, e.problem) from None
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if decoded is None:
        raise invalid("image", "cannot decode image (corrupt PNG or JPEG file)")
    rgb = cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
    labels = models.predict(sha, rgb)
    return {
        "model_id": model_id,
        "model": name,
        "width": int(rgb.shape[1]),
        "height": int(rgb.shape[0]),
        "overlay": b64png(overlay(rgb, labels)),
        "labels": b64png(colorize(labels)),
        "legend": legend(labels),
    }
