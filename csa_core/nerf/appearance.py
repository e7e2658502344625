"""Per-frame colour correction: real cameras change exposure and white balance between frames.

Kinect-style sensors adjust exposure and white balance on their own, so the same surface has a
different colour in different frames. A single radiance field can only average those colours
(blur, and colour error on every view). ``FrameAppearance`` gives every training frame an
affine colour correction ``observed = gain * rgb + bias`` per channel (6 numbers per frame;
the appearance embedding of NeRF-W / nerfacto reduced to an exposure and white-balance model).

The corrections are made zero-mean over the training frames (log-gains and biases), so the
field itself holds the average appearance: a camera that is not a training frame renders with
no correction (``frame=None``), or with the correction of a chosen training frame (e.g. the
nearest one).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn


class FrameAppearance(nn.Module):
    """Affine colour correction per training frame, parameters ``(num_frames, 6)``:
    log-gain (3) and bias (3), zero-mean over frames."""

    def __init__(self, num_frames: int):
        super().__init__()
        self.params = nn.Parameter(torch.zeros(num_frames, 6))

    @property
    def num_frames(self) -> int:
        return int(self.params.shape[0])

    def centered(self) -> Tensor:
        """Parameters minus their mean over frames ``(F, 6)``."""
        return self.params - self.params.mean(dim=0, keepdim=True)

    def forward(self, rgb: Tensor, frames: Tensor | int | None) -> Tensor:
        """Apply the correction of training frame(s) ``frames`` (R,) or one index to ``rgb`` (R, 3);
        ``None`` returns ``rgb`` unchanged (the field's average appearance)."""
        if frames is None:
            return rgb
        p = self.centered()[frames]
        if p.dim() == 1:
            p = p.unsqueeze(0)
        return rgb * torch.exp(p[:, :3]) + p[:, 3:]


def nearest_frame(poses: np.ndarray, pose: np.ndarray, metres_per_radian: float = 1.0) -> int:
    """Index of the pose in ``poses`` (F, 4, 4) closest to ``pose``: camera-centre distance plus
    ``metres_per_radian`` times the angle between the viewing directions."""
    poses = np.asarray(poses, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    dist = np.linalg.norm(poses[:, :3, 3] - pose[:3, 3], axis=1)
    cos = np.clip(poses[:, :3, 2] @ pose[:3, 2], -1.0, 1.0)
    return int(np.argmin(dist + metres_per_radian * np.arccos(cos)))
