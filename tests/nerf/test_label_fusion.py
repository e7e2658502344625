"""Label fusion: view-inconsistent label errors are removed by fitting one 3D model.

Every training frame's ground-truth labels are corrupted independently (wrong-class blobs,
partly swapped objects, ragged edges). Labels rendered back at the training views must be
better than the corrupted inputs: at least MARGIN mIoU points.
"""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.data.label_noise import LabelNoiseConfig, corrupt_labels
from csa_core.eval.miou import ConfusionMatrix
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.render import render_pseudo_labels
from tests.nerf.conftest import synthetic_scene, tiny_config

# Rendered labels must beat the corrupted inputs by 4 mIoU points. Measured +15.6 (0.417 ->
# 0.573) on rooms of boxes, +4.6 to +5.0 (0.399 -> 0.445-0.449) since the room has thin parts:
# at 48x36 and 400 steps the tiny NeRF loses 2 cm chair legs and slats and thin table legs
# (chair IoU 0.29 -> 0.27, table 0.40 -> 0.23) while walls and floor gain 15 and 33 points.
MARGIN = 0.04


@pytest.mark.slow
def test_rendered_labels_beat_view_inconsistent_corruption():
    scene = synthetic_scene(frames=30, size=(48, 36), seed=3)
    rng = np.random.default_rng(0)
    for f in scene.frames:
        f.labels["noisy"] = corrupt_labels(f.labels["label-nyu40"], rng, LabelNoiseConfig())
    cfg = tiny_config(steps=400)
    cfg.optim.rays_per_step = 512
    nerf, _ = fit_semantic_nerf(scene, "noisy", cfg, device="cpu", progress=False)
    rendered = render_pseudo_labels(nerf, scene, views="train")
    before, after = ConfusionMatrix(), ConfusionMatrix()
    for f in scene.train_frames:
        gt = f.labels["label-nyu40"]
        before.update(f.labels["noisy"], gt)
        after.update(rendered[f.name], gt)
    print(f"mIoU corrupted {before.miou():.3f} -> rendered {after.miou():.3f}")
    assert before.miou() < 0.8  # the corruption is substantial
    assert after.miou() >= before.miou() + MARGIN
    assert after.pixel_accuracy() > before.pixel_accuracy()
