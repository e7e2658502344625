"""Per-frame colour correction: identity at start, learns exposure, deterministic, survives
checkpoints."""

from __future__ import annotations

import numpy as np
import torch

from csa_core.nerf.appearance import FrameAppearance, nearest_frame
from csa_core.nerf.checkpoint import load_checkpoint, save_checkpoint
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.render import render_image
from tests.nerf.conftest import synthetic_scene, tiny_config
from tests.tiny_scenes import look_at_pose

GAINS = (0.6, 1.0, 1.4)  # exposure of frame i is GAINS[i % 3]


def exposed_scene():
    scene = synthetic_scene(frames=9, size=(32, 24), seed=1)
    for i, f in enumerate(scene.frames):
        f.color = (
            np.clip(f.color.astype(np.float64) * GAINS[i % 3], 0, 255).round().astype(np.uint8)
        )
    return scene


def log_gain_by_exposure(nerf, scene) -> list[float]:
    """Mean log-gain of the colour corrections of the training frames of each exposure."""
    gain = nerf.appearance.centered()[:, :3].mean(dim=1).detach()
    train = len(scene.train_frames)
    return [
        float(gain[[i for i in range(train) if i % len(GAINS) == k]].mean())
        for k in range(len(GAINS))
    ]


def fit_with_corrections(scene, steps=150):
    cfg = tiny_config(steps=steps)
    cfg.appearance = "affine"
    return fit_semantic_nerf(scene, "label-nyu40", cfg, device="cpu", progress=False)[0]


def test_corrections_start_as_identity_and_stay_zero_mean():
    app = FrameAppearance(4)
    rgb = torch.rand(5, 3)
    assert torch.equal(app(rgb, torch.tensor([0, 1, 2, 3, 0])), rgb)
    assert torch.equal(app(rgb, None), rgb)
    with torch.no_grad():
        app.params.copy_(torch.randn(4, 6))
    assert torch.allclose(app.centered().mean(dim=0), torch.zeros(6), atol=1e-6)
    one = app(rgb, 2)
    per_ray = app(rgb, torch.full((5,), 2))
    assert torch.allclose(one, per_ray)
    p = app.centered()[2]
    assert torch.allclose(one, rgb * torch.exp(p[:3]) + p[3:])


def test_fit_learns_each_frames_exposure_and_is_deterministic():
    scene = exposed_scene()
    a, b = fit_with_corrections(scene), fit_with_corrections(scene)
    assert torch.equal(a.appearance.params, b.appearance.params)
    by_exposure = log_gain_by_exposure(a, scene)
    assert by_exposure[0] < by_exposure[1] < by_exposure[2], by_exposure
    # The field holds the average appearance: a bright training frame renders darker without its
    # correction than with it.
    f = scene.train_frames[2]
    plain = render_image(a, f.pose, semantics=False).color.astype(float).mean()
    own = render_image(a, f.pose, semantics=False, appearance=2).color.astype(float).mean()
    assert own > plain + 5


def test_checkpoint_round_trip_keeps_the_corrections_bit_exact(tmp_path):
    scene = exposed_scene()
    nerf = fit_with_corrections(scene, steps=20)
    for dtype in ("float32", "float16"):
        path = tmp_path / f"{dtype}.safetensors"
        save_checkpoint(nerf, path, dtype=dtype)
        loaded = load_checkpoint(path)
        assert torch.equal(loaded.appearance.params, nerf.appearance.params)  # stored in float32
        if dtype == "float32":
            pose = scene.frames[-1].pose
            for k in (None, 3):
                x = render_image(nerf, pose, appearance=k)
                y = render_image(loaded, pose, appearance=k)
                assert np.array_equal(x.color, y.color) and np.array_equal(x.labels, y.labels)


def test_a_model_without_corrections_ignores_the_appearance_argument(tiny_nerf, tiny_scene):
    assert tiny_nerf.appearance is None
    pose = tiny_scene.frames[0].pose
    a = render_image(tiny_nerf, pose, semantics=False)
    b = render_image(tiny_nerf, pose, semantics=False, appearance=1)
    assert np.array_equal(a.color, b.color)


def test_nearest_frame_weighs_position_and_viewing_direction():
    poses = np.stack(
        [
            look_at_pose([0, 0, 1], [1, 0, 1]),
            look_at_pose([0.3, 0, 1], [1, 0, 1]),
            look_at_pose([0.05, 0, 1], [-1, 0, 1]),  # close, but looking the other way
        ]
    )
    assert nearest_frame(poses, look_at_pose([0.1, 0, 1], [1, 0, 1])) == 0
    assert nearest_frame(poses, look_at_pose([0.28, 0, 1], [1, 0.1, 1])) == 1
    assert nearest_frame(poses, look_at_pose([0.1, 0, 1], [-1, 0, 1])) == 2
