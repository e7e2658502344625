"""The Mapping baseline (Frey et al., RA-L 2022): fuse per-frame predictions in a voxel map,
read pseudo-labels back at each training view, fine-tune on camera images + map labels (GI+ML).

Unlike the NeRF, the map cannot render new images, so replaying an old scene means keeping its
training images and map labels explicitly; :class:`MappingMemory` holds them and its size is
the Mapping row of the memory-footprint table (docs/method.md, "Protocols and metrics").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from csa_core.adapt.baselines.voxel_map import VoxelMapConfig, VoxelSemanticMap
from csa_core.data.scene import Frame, Scene
from csa_core.errors import CSAInputError

if TYPE_CHECKING:
    import torch

    from csa_core.adapt.replay import ReplayBuffer

MAPPING_FOLDER = "label-mapping"  # label folder name for the map's pseudo-labels


def _frames_by_name(scene: Scene, names: Sequence[str]) -> list[Frame]:
    by_name = {f.name: f for f in scene.frames}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise CSAInputError(
            f"scene {scene.name}", f"no frame(s) named {', '.join(map(str, missing[:5]))}"
        )
    return [by_name[n] for n in names]


def _check_prediction(scene: Scene, frame: Frame, prediction: np.ndarray) -> np.ndarray:
    prediction = np.asarray(prediction)
    h, w = frame.color.shape[:2]
    if prediction.shape[:2] != (h, w) or prediction.ndim not in (2, 3):
        raise CSAInputError(
            f"scene {scene.name}",
            f"prediction of frame {frame.name} has shape {prediction.shape}, image is {h}x{w}",
        )
    return prediction


def build_voxel_map(
    scene: Scene,
    predictions: Mapping[str, np.ndarray],
    config: VoxelMapConfig | None = None,
    device: str | torch.device | None = None,
    backend: str = "torch",
) -> VoxelSemanticMap:
    """Fuse ``predictions`` (frame name -> (H, W) NYU40 labels or (H, W, C) probabilities)
    into a voxel map using each frame's depth and pose, on ``device`` (default CPU; ``backend``
    "numpy" is the map's reference implementation). Frames without depth add nothing; a scene
    where no predicted frame has depth is an input error (Mapping needs depth)."""
    frames = _frames_by_name(scene, list(predictions))
    voxel_map = VoxelSemanticMap(config, device=device, backend=backend)
    if frames and not any(f.depth is not None and f.depth_mask.any() for f in frames):
        raise CSAInputError(
            scene.root or f"scene {scene.name}", "Mapping needs depth, and no frame has any"
        )
    for frame in frames:
        if frame.depth is None:
            continue
        prediction = _check_prediction(scene, frame, predictions[frame.name])
        voxel_map.integrate(prediction, frame.depth, frame.pose, scene.intrinsics)
    return voxel_map


READ_BACKS = ("raycast", "depth")


def render_map_labels(
    voxel_map: VoxelSemanticMap, scene: Scene, names: Sequence[str], read: str = "raycast"
) -> dict[str, np.ndarray]:
    """Pseudo-labels of the named frames read from the map. ``read="raycast"`` (Frey et al.):
    each pixel's ray is cast from the frame's pose to the zero crossing of the map's TSDF
    (:meth:`VoxelSemanticMap.raycast`) and takes the class votes there, 0 only where it meets
    no surface (or no votes lie near it), so pixels the sensor missed are labelled too.
    ``read="depth"``: the voxel at each pixel's own measured surface point, 0 where the frame
    has no depth (the older read-back, kept for comparison)."""
    if read not in READ_BACKS:
        raise ValueError(f"render_map_labels: read must be one of {READ_BACKS}, got {read!r}")
    out: dict[str, np.ndarray] = {}
    for frame in _frames_by_name(scene, names):
        if read == "raycast":
            out[frame.name] = voxel_map.labels_for_pose(frame.pose, scene.intrinsics)
        elif frame.depth is None:
            out[frame.name] = np.zeros(frame.color.shape[:2], dtype=np.uint8)
        else:
            out[frame.name] = voxel_map.labels_at_depth(frame.depth, frame.pose, scene.intrinsics)
    return out


def mapping_pseudo_labels(
    scene: Scene,
    predictions: Mapping[str, np.ndarray],
    config: VoxelMapConfig | None = None,
    device: str | torch.device | None = None,
) -> dict[str, np.ndarray]:
    """Mapping's pseudo-labels: fuse the predicted frames, read the map back at the same frames."""
    voxel_map = build_voxel_map(scene, predictions, config, device)
    return render_map_labels(voxel_map, scene, list(predictions))


def _encoded_bytes(image: np.ndarray, ext: str) -> int:
    data = image[..., ::-1] if image.ndim == 3 else image  # OpenCV encodes BGR
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(data))
    if not ok:
        raise ValueError(f"could not encode an image as {ext}")
    return int(buf.size)


@dataclass(frozen=True)
class MappingFootprint:
    """Bytes Mapping keeps per scene: the voxel map, and the training images and map labels
    it must store to replay the scene later (raw arrays, or encoded files when asked)."""

    map_bytes: int
    image_bytes: int
    label_bytes: int
    num_images: int

    @property
    def replay_bytes(self) -> int:
        return self.image_bytes + self.label_bytes

    @property
    def total_bytes(self) -> int:
        return self.map_bytes + self.replay_bytes


@dataclass
class MappingMemory:
    """What Mapping remembers of one scene for replay: its training images and map labels."""

    scene: str
    images: list[np.ndarray]
    labels: list[np.ndarray]
    names: list[str] = field(default_factory=list)
    map_bytes: int = 0

    def __len__(self) -> int:
        return len(self.images)

    def footprint(self, encode: str | None = None) -> MappingFootprint:
        """Stored bytes; ``encode`` (``".png"``, ``".jpg"``) counts files instead of raw arrays
        (labels are always counted as PNG then, since they must stay lossless)."""
        if encode is None:
            img = sum(int(i.nbytes) for i in self.images)
            lab = sum(int(x.nbytes) for x in self.labels)
        else:
            img = sum(_encoded_bytes(i, encode) for i in self.images)
            lab = sum(_encoded_bytes(x, ".png") for x in self.labels)
        return MappingFootprint(self.map_bytes, img, lab, len(self.images))


def mapping_replay_buffer(memories: Sequence[MappingMemory], size: int) -> ReplayBuffer:
    """A replay buffer of ``size`` stored pairs from earlier scenes, split and picked by the
    same rule as the NeRF replay (equal shares, views evenly spaced along each trajectory),
    so Mapping and CSA see the same batch composition (docs/method.md "Remember" fixes ``size`` at
    100)."""
    from csa_core.adapt.replay import ReplayBuffer, evenly_spaced, split_buffer

    buffer = ReplayBuffer()
    for memory, share in zip(memories, split_buffer(size, len(memories)), strict=True):
        for k in evenly_spaced(len(memory), share):
            buffer.images.append(memory.images[k])
            buffer.labels.append(memory.labels[k])
            name = memory.names[k] if memory.names else str(k)
            buffer.names.append(f"{memory.scene}/{name}")
            buffer.sources.append(memory.scene)
    return buffer


def mapping_memory(
    scene: Scene,
    pseudo_labels: Mapping[str, np.ndarray],
    voxel_map: VoxelSemanticMap | None = None,
) -> MappingMemory:
    """The replay memory of a scene: the camera images of the labelled frames and their map
    labels."""
    frames = _frames_by_name(scene, list(pseudo_labels))
    return MappingMemory(
        scene=scene.name,
        images=[f.color for f in frames],
        labels=[np.asarray(pseudo_labels[f.name], dtype=np.uint8) for f in frames],
        names=[f.name for f in frames],
        map_bytes=voxel_map.nbytes if voxel_map is not None else 0,
    )
