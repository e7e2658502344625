"""Tiny scenes and a tiny, quickly fitted NeRF shared by the NeRF tests."""

from __future__ import annotations

import pytest

from csa_core.data.scene import Scene
from csa_core.nerf.config import NerfConfig, preset


def tiny_config(steps: int = 40) -> NerfConfig:
    """The fast preset shrunk so a fit takes about a second on one CPU core."""
    cfg = preset("fast")
    enc = cfg.field.encoding
    enc.num_levels, enc.log2_table_size, enc.finest_resolution = 6, 12, 128
    cfg.optim.steps = steps
    cfg.optim.rays_per_step = 256
    # Uniform draws and no semantic steps after the fit, so a fit stays about a second; the
    # preset's label-fusion draws and steps have tests of their own (tests/nerf/test_trainer.py).
    cfg.optim.ray_batches = "all"
    cfg.optim.semantic_steps, cfg.optim.semantic_rays_per_step = 0, 256
    cfg.optim.semantic_lr_fraction = 1.0
    # The paper's semantic loss, whose class distributions the render tests' tolerances were
    # set for; the preset's Semantic-NeRF loss has tests of its own
    # (tests/experiments/test_semantic_loss_form.py, tests/nerf/test_holes_and_unseen.py).
    cfg.loss.semantic_form = "paper"
    # Labels everywhere: unseen surfaces left unknown have tests of their own
    # (tests/nerf/test_holes_and_unseen.py).
    cfg.render_unseen_unknown, cfg.observed_resolution = False, 0
    # Labels from the whole band: the preset's cut behind the measured depth and its share
    # of the surface point's labels have tests of their own
    # (tests/nerf/test_holes_and_unseen.py).
    cfg.sampler.render_band_label_behind, cfg.sampler.render_surface_label_weight = None, 0.0
    cfg.sampler.occupancy_resolution = 32
    cfg.sampler.march_steps = 192
    cfg.sampler.uniform_samples = cfg.sampler.importance_samples = 32
    cfg.render_chunk = 2048
    return cfg


def synthetic_scene(frames: int = 10, size=(32, 24), seed: int = 0) -> Scene:
    from csa_core.data.synth import generate_scene

    return generate_scene("apartment", seed, frames, size)


@pytest.fixture(scope="session")
def tiny_scene() -> Scene:
    return synthetic_scene()


@pytest.fixture(scope="session")
def tiny_nerf(tiny_scene):
    from csa_core.nerf.fit import fit_semantic_nerf

    nerf, _ = fit_semantic_nerf(
        tiny_scene, "label-nyu40", tiny_config(steps=150), device="cpu", progress=False
    )
    return nerf
