"""Camera rays: pixel directions, the rays of an image, and a bank of all training pixels.

Rays use unit-z camera directions (the direction of pixel ``(u, v)`` is
``((u - cx) / fx, (v - cy) / fy, 1)`` rotated to the world), so the ray parameter ``t`` is
metric z-depth and rendered depth needs no conversion.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from csa_core.data.camera import Intrinsics
from csa_core.data.scene import Frame
from csa_core.nerf.losses import near_view_weight


def camera_directions(intr: Intrinsics, device: torch.device | str = "cpu") -> Tensor:
    """Unit-z camera-frame directions of every pixel centre, (H * W, 3), row-major."""
    v, u = torch.meshgrid(
        torch.arange(intr.height, dtype=torch.float64),
        torch.arange(intr.width, dtype=torch.float64),
        indexing="ij",
    )
    d = torch.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, torch.ones_like(u)], dim=-1)
    return d.reshape(-1, 3).to(device=device, dtype=torch.float32)


def image_rays(
    intr: Intrinsics, pose: np.ndarray, device: torch.device | str = "cpu"
) -> tuple[Tensor, Tensor]:
    """World origins and unit-z directions (H * W, 3) of every pixel of a camera at ``pose``."""
    p = torch.as_tensor(np.asarray(pose, dtype=np.float64), dtype=torch.float32, device=device)
    d = camera_directions(intr, device) @ p[:3, :3].T
    return p[:3, 3].expand_as(d).contiguous(), d


def frame_depth(frame: Frame) -> np.ndarray:
    """The frame's depth in metres (H, W) float32, zeros where (or when) nothing was measured."""
    if frame.depth is None:
        return np.zeros(frame.color.shape[:2], np.float32)
    return np.asarray(frame.depth, dtype=np.float32)


class RayBank:
    """All pixels of posed frames as flat tensors: colour, depth (0 = not measured), optional
    labels (0 = ignored) and each pixel's frame. Pixel ``i`` is pixel ``i % (H * W)`` of frame
    ``i // (H * W)``. ``frame_rows`` maps each frame to its row of per-frame parameters (the
    model's colour corrections); by default frame ``k`` is row ``k``."""

    def __init__(
        self,
        frames: Sequence[Frame],
        intr: Intrinsics,
        device: torch.device | str = "cpu",
        label_folder: str | None = None,
        frame_rows: Tensor | None = None,
    ):
        self.frames = list(frames)
        self.device = torch.device(device)
        self.hw = intr.width * intr.height
        self.dirs_cam = camera_directions(intr, device)
        poses = torch.as_tensor(
            np.stack([np.asarray(f.pose, dtype=np.float64) for f in self.frames]),
            dtype=torch.float32,
            device=device,
        )
        self.rot = poses[:, :3, :3]
        self.origin = poses[:, :3, 3]
        self.rgb = torch.as_tensor(
            np.stack([f.color for f in self.frames]).reshape(-1, 3), device=device
        )
        self.depth = torch.as_tensor(
            np.stack([frame_depth(f) for f in self.frames]).reshape(-1), device=device
        )
        self.has_depth = bool((self.depth > 0).any())
        self._median_depth: float | None = None
        self._width = intr.width
        self.frame_rows = frame_rows
        self.labels: Tensor | None = None
        self._balanced: tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None = None
        if label_folder is not None:
            self.set_labels({f.name: f.labels[label_folder] for f in self.frames})

    @property
    def count(self) -> int:
        return int(self.rgb.shape[0])

    def set_labels(self, labels: Mapping[str, np.ndarray]) -> None:
        """Semantic targets ``{frame name: (H, W) NYU40 ids}`` for every frame of the bank."""
        missing = [f.name for f in self.frames if f.name not in labels]
        if missing:
            raise KeyError(f"no labels for frame(s) {', '.join(missing[:5])}")
        stack = np.stack([np.asarray(labels[f.name], dtype=np.uint8) for f in self.frames])
        if stack.shape[1] * stack.shape[2] != self.hw:
            raise ValueError(
                f"labels are {stack.shape[2]}x{stack.shape[1]}, frames have {self.hw} pixels"
            )
        self.labels = torch.as_tensor(stack.reshape(-1), device=self.device)
        self._balanced = None

    def _class_strata(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Pixel ids sorted by label, and per label id (0..255): first position, count, the
        share of draws ``RayBank.balanced_ids`` gives it and the weight of a drawn pixel."""
        if self._balanced is None:
            assert self.labels is not None
            labels = self.labels.long()
            order = torch.argsort(labels, stable=True)
            counts = torch.bincount(labels, minlength=256)
            starts = torch.cumsum(counts, 0) - counts
            share = counts.double() / counts.sum()
            root = counts.double().sqrt()
            draw = 0.5 * share + 0.5 * root / root.sum()
            weight = (share / draw).float()  # NaN only for labels never drawn (q = 0)
            self._balanced = (order, starts, counts, draw, weight)
        return self._balanced

    def balanced_ids(
        self, n: int, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """``n`` pixel ids drawn label-stratified, and their importance weights (mean 1 over
        the bank). A label id with share ``p`` of the pixels is drawn with probability
        ``q = p / 2 + sqrt(count) / (2 * sum sqrt(counts))``, so rare labels are drawn more
        often than uniformly (and no label less than half as often), and a drawn pixel
        weighs ``p / q``: weighted, every loss keeps its expectation under uniform draws (and
        so its optimum), with less variance on the rare labels."""
        if self.labels is None:
            raise ValueError("balanced ray draws need labels (RayBank.set_labels)")
        order, starts, counts, draw, weight = self._class_strata()
        cls = torch.multinomial(draw.float(), n, replacement=True, generator=generator)
        u = torch.rand(n, device=self.device, generator=generator, dtype=torch.float64)
        offset = (u * counts[cls].double()).long().clamp_max(counts[cls] - 1)
        return order[starts[cls] + offset], weight[cls]

    def random_ids(
        self, n: int, generator: torch.Generator | None = None, frame: int | None = None
    ) -> Tensor:
        """``n`` pixel ids drawn uniformly (with replacement) from all frames, or from frame
        number ``frame`` alone (the official code's ray batches: one image per step)."""
        if frame is None:
            return torch.randint(0, self.count, (n,), device=self.device, generator=generator)
        if not 0 <= frame < len(self.frames):
            raise IndexError(f"frame {frame} of a bank of {len(self.frames)} frames")
        pix = torch.randint(0, self.hw, (n,), device=self.device, generator=generator)
        return pix + frame * self.hw

    def near_weights(self, ids: Tensor, power: float) -> Tensor | None:
        """Semantic-loss weights of pixels ``ids`` by their depth, near views favoured when
        ``power`` > 0 and far ones when it is < 0 (``losses.near_view_weight`` relative to the
        bank's median measured depth), or None when ``power`` is 0 or the bank has no depth."""
        if power == 0 or not self.has_depth:
            return None
        if self._median_depth is None:
            self._median_depth = float(self.depth[self.depth > 0].median())
        return near_view_weight(self.depth[ids], power, self._median_depth)

    def beside_nearer_surface(self, half_width: Callable[[Tensor], Tensor]) -> Tensor:
        """Whether each pixel (bool, flat like the bank) has a measured depth in its 3x3
        neighbourhood more than ``half_width(depth)`` in front of its own measured depth
        (``SamplerConfig.band_half_width``): its ray passes just beside an edge of a nearer
        surface. Pixels without depth, and neighbours without depth, never count."""
        h, w = self.hw // self._width, self._width
        out = torch.zeros(self.count, dtype=torch.bool, device=self.device)
        per_chunk = max(1, 2**22 // self.hw)  # frames per chunk: a few MB of temporaries
        for start in range(0, len(self.frames), per_chunk):
            stop = min(start + per_chunk, len(self.frames))
            depth = self.depth[start * self.hw : stop * self.hw].view(stop - start, 1, h, w)
            far = torch.where(depth > 0, depth, torch.full_like(depth, float("inf")))
            nearest = -F.max_pool2d(-far, kernel_size=3, stride=1, padding=1)
            edge = (depth > 0) & (depth - nearest > half_width(depth))
            out[start * self.hw : stop * self.hw] = edge.reshape(-1)
        return out

    def surface_points(self, chunk: int = 2**18) -> Iterator[Tensor]:
        """World points (N, 3) of every pixel with measured depth, in chunks of pixels."""
        for start in range(0, self.count, chunk):
            ids = torch.arange(start, min(start + chunk, self.count), device=self.device)
            ids = ids[self.depth[ids] > 0]
            if ids.numel():
                origins, dirs = self.rays(ids)
                yield origins + dirs * self.depth[ids, None]

    def rays(self, ids: Tensor) -> tuple[Tensor, Tensor]:
        """World origins and unit-z directions (N, 3) of pixels ``ids``."""
        cam, pix = ids // self.hw, ids % self.hw
        dirs = torch.einsum("nij,nj->ni", self.rot[cam], self.dirs_cam[pix])
        return self.origin[cam], dirs

    def batch(self, ids: Tensor) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """Rays of pixels ``ids`` and their targets: ``rgb`` in [0, 1], ``depth``, ``frame``
        (row of per-frame parameters) and, when set, ``labels``."""
        origins, dirs = self.rays(ids)
        cam = ids // self.hw
        target = {
            "rgb": self.rgb[ids].float() / 255.0,
            "depth": self.depth[ids],
            "frame": cam if self.frame_rows is None else self.frame_rows[cam],
        }
        if self.labels is not None:
            target["labels"] = self.labels[ids]
        return origins, dirs, target
