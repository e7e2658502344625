"""Shared fixtures: tiny scenes built in a temp folder, and the real 7-Scenes frames."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from csa_core.data.scene import Scene
from tests.tiny_scenes import make_random_scene

REPO = Path(__file__).resolve().parents[1]
SEVEN_SCENES = REPO.parent / "shared" / "data" / "7scenes-kitchen-100"

# One thread policy for the whole suite (tiny tensors everywhere): on an idle 2-core machine
# two threads are about 10% faster (2m35s vs 2m53s), but on a shared one they spin against
# each other and some tests ran 5-20x slower.
torch.set_num_threads(1)


@pytest.fixture
def seven_scenes_dir() -> Path:
    if not SEVEN_SCENES.is_dir():
        pytest.skip(f"7-Scenes frames not found next to the repository ({SEVEN_SCENES})")
    return SEVEN_SCENES


@pytest.fixture
def random_scene() -> Scene:
    return make_random_scene()
