"""Image/label pairs for training and scoring segmentation networks."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from csa_core.data.nyu40 import check_label_map
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.errors import CSAInputError
from csa_core.seg.transforms import image_to_tensor, to_float_image

PairTransform = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]


class SegmentationDataset(Dataset[tuple[Tensor, Tensor]]):
    """Pairs of (H, W, 3) uint8 RGB images and (H, W) uint8 NYU40 label maps (0 = unknown).

    Items are ``(image, labels)``: a (3, H, W) float32 image in [0, 1] and an (H, W) int64
    map of NYU40 ids, after the optional joint ``transform`` (applied to the uint8 image).
    The pairs can come from camera frames, rendered views or pseudo-labels alike.
    """

    def __init__(
        self,
        images: Sequence[np.ndarray],
        labels: Sequence[np.ndarray],
        transform: PairTransform | None = None,
        names: Sequence[str] | None = None,
    ):
        if len(images) != len(labels):
            raise ValueError(
                f"SegmentationDataset: {len(images)} images but {len(labels)} label maps"
            )
        self.names = list(names) if names is not None else [str(i) for i in range(len(images))]
        if len(self.names) != len(images):
            raise ValueError(
                f"SegmentationDataset: {len(self.names)} names for {len(images)} images"
            )
        for name, img, lab in zip(self.names, images, labels, strict=True):
            check_label_map(lab, f"labels of {name}")
            if img.shape[:2] != lab.shape:
                raise ValueError(
                    f"SegmentationDataset: {name}: image {img.shape[:2]} and labels {lab.shape} "
                    "differ in size"
                )
        self.images = list(images)
        self.labels = list(labels)
        self.transform = transform

    @classmethod
    def from_scenes(
        cls,
        scenes: Scene | Sequence[Scene],
        split: str = "train",
        label_folder: str = NYU40_FOLDER,
        transform: PairTransform | None = None,
    ) -> SegmentationDataset:
        """The ``split`` frames (``train``, ``val`` or ``all``) of scenes, labelled by
        ``label_folder``."""
        scenes = [scenes] if isinstance(scenes, Scene) else list(scenes)
        images: list[np.ndarray] = []
        labels: list[np.ndarray] = []
        names: list[str] = []
        for scene in scenes:
            for frame in scene.split(split):
                if label_folder not in frame.labels:
                    where = (
                        scene.root / label_folder
                        if scene.root is not None
                        else f"scene {scene.name}"
                    )
                    raise CSAInputError(where, f"frame {frame.name} has no '{label_folder}' labels")
                images.append(frame.color)
                labels.append(frame.labels[label_folder])
                names.append(f"{scene.name}/{frame.name}")
        return cls(images, labels, transform=transform, names=names)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> tuple[Tensor, Tensor]:
        image = image_to_tensor(self.images[index])
        labels = torch.from_numpy(np.ascontiguousarray(self.labels[index]))
        if self.transform is not None:
            image, labels = self.transform(image, labels)
        return to_float_image(image), labels.long()
