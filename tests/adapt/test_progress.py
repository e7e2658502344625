"""``adapt_one_step``'s ``on_progress``: NeRF fit steps, fine-tuning epochs or joint rounds,
then the end, in order; an exception from it stops the step and propagates unchanged."""

from __future__ import annotations

import copy

import pytest

from csa_core.adapt.modes import adapt_one_step
from tests.adapt.conftest import tiny_config


class Stop(Exception):
    """What a caller raises to stop the step (the service raises JobCancelled)."""


def test_joint_step_reports_nerf_steps_rounds_and_the_end(pretrained, target_scenes) -> None:
    calls: list[tuple[str, float]] = []
    config = tiny_config("joint")
    config.collapse.enabled = False  # both rounds run
    adapt_one_step(
        copy.deepcopy(pretrained),
        target_scenes[0],
        config,
        on_progress=lambda message, fraction: calls.append((message, fraction)),
    )
    fractions = [f for _, f in calls]
    assert fractions == sorted(fractions) and 0.0 < fractions[0] and fractions[-1] == 1.0
    messages = [m for m, _ in calls]
    assert messages[0].startswith(f"NeRF step 1/{config.nerf.prefit_steps}")
    rounds = [m.split("  ")[0] for m in messages if m.startswith("joint round")]
    # inside every round: after the network's epochs, after the NeRF's steps, at its end
    assert rounds == [
        "joint round 1/2: network trained",
        "joint round 1/2: NeRF trained",
        "joint round 1/2",
        "joint round 2/2: network trained",
        "joint round 2/2: NeRF trained",
        "joint round 2/2",
    ]


def test_an_exception_stops_the_fine_tuning(pretrained, target_scenes) -> None:
    config = tiny_config("gi_nl")
    config.seg.epochs = 20
    config.collapse.enabled = False
    epochs: list[str] = []
    stop = Stop("cancelled")

    def cancel_at_first_epoch(message: str, fraction: float) -> None:
        if message.startswith("epoch"):
            epochs.append(message)
            raise stop

    with pytest.raises(Stop) as raised:
        adapt_one_step(
            copy.deepcopy(pretrained), target_scenes[0], config, on_progress=cancel_at_first_epoch
        )
    assert raised.value is stop and len(epochs) == 1 and epochs[0].startswith("epoch 1/20")
