"""The continual step: replay from any memory bank at the config's sample cap, what the
collapse guard leaves behind (a stopped joint training restores the NeRF with the network;
a skipped scene banks no NeRF and no BatchNorm statistics), and which renders make images."""

from __future__ import annotations

import copy

import pytest
import torch

import csa_core.adapt.finetune as finetune
from csa_core.adapt.memory_bank import MemoryBank
from csa_core.adapt.methods import ContinualState
from csa_core.adapt.modes import adapt_one_step
from csa_core.adapt.pseudo_labels import label_miou, render_pairs
from csa_core.adapt.step import continual_step
from csa_core.seg.adabn import batchnorm_layers
from tests.adapt.conftest import tiny_config


def _state_dict(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def _equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def force_decisions(monkeypatch, actions: dict[str, str]) -> None:
    """The guard measures as usual but decides ``actions[stage]`` (default ``continue``) at
    every check: the pre-fit (``prefit`` / ``pseudo_labels``) and each joint round."""
    real = finetune.check_labels

    def check(stage, labels, pseudo, config, prior_entropy, in_joint=False):
        decision = real(stage, labels, pseudo, config, prior_entropy, in_joint)
        decision.action = actions.get(stage, "continue")
        return decision

    monkeypatch.setattr(finetune, "check_labels", check)
    monkeypatch.setattr("csa_core.adapt.joint.check_labels", check)


class RecordingBank(MemoryBank):
    """A folder memory bank that keeps every NeRF it hands out (any ``NerfMemory`` will do)."""

    def __init__(self, folder):
        super().__init__(folder)
        self.loaded = []
        self.devices = []

    def load(self, scene, device="cpu"):
        nerf = super().load(scene, device)
        self.loaded.append(nerf)
        self.devices.append(device)
        return nerf


def test_step_replays_from_the_bank_at_the_configs_sample_cap(pretrained, target_scenes, tmp_path):
    config = tiny_config("gi_nl")
    config.collapse.enabled = False
    config.replay.max_render_samples = 7
    bank = RecordingBank(tmp_path / "memory")
    state = ContinualState.start(config, bank=bank)
    model = copy.deepcopy(pretrained)
    first = continual_step(state, model, target_scenes[0])
    assert first["replay"] == {} and bank.loaded == []
    second = continual_step(state, model, target_scenes[1])
    assert second["replay"] == {target_scenes[0].name: config.replay.buffer_size}
    (replayed,) = bank.loaded
    assert replayed.config.sampler.max_render_samples == 7
    assert bank.devices == [config.seg.device] == ["cpu"]  # replay renders where the step trains
    assert bank.scenes == [s.name for s in target_scenes[:2]]
    assert list(state.batchnorm.scenes) == bank.scenes == second["batchnorm_pooled"]
    assert second["memory_bytes"]["nerf_total"] == sum(bank.bytes_per_scene().values())
    assert second["memory_bytes"]["batchnorm_statistics"] == state.batchnorm.nbytes() > 0


def test_stopped_joint_training_restores_the_nerf_with_the_network(
    pretrained, target_scenes, tmp_path, monkeypatch
):
    """Round 1 passes, the guard stops at round 2: the NeRF that trained in place on round
    2's labels goes back to its state after round 1, and that state is what gets banked."""
    snapshots: list[dict[str, torch.Tensor]] = []
    round_labels = []

    def renders(nerf, scene, color=True):
        snapshots.append(_state_dict(nerf))
        images, labels = render_pairs(nerf, scene, color)
        round_labels.append(labels)
        return images, labels

    monkeypatch.setattr("csa_core.adapt.joint.render_pairs", renders)
    force_decisions(monkeypatch, {"round 2": "stop_joint"})
    config = tiny_config("joint")
    config.joint.rounds = 3
    scene = target_scenes[0]
    state = ContinualState.start(config, bank=MemoryBank(tmp_path / "memory"))
    record = continual_step(state, copy.deepcopy(pretrained), scene)

    assert [d["action"] for d in record["decisions"]] == ["continue", "continue", "stop_joint"]
    assert len(snapshots) == 2 and not _equal(snapshots[0], snapshots[1])
    banked = state.bank.load(scene.name)
    # The bank holds the NeRF after round 1 (stored at the config's dtype, so compare with
    # that state stored the same way) ...
    reference = copy.deepcopy(banked)
    reference.load_state_dict(snapshots[0])
    reference_bank = MemoryBank(tmp_path / "reference")
    reference_bank.add(scene.name, reference)
    assert _equal(_state_dict(banked), _state_dict(reference_bank.load(scene.name)))
    # ... whose labels are the ones reported as the final NeRF labels.
    assert record["final_label_miou"] == label_miou(round_labels[0], scene)
    assert record["trained"] and state.batchnorm.scenes.keys() == {scene.name}


def test_stop_joint_rolls_back_nerf_and_network_in_place(pretrained, target_scenes, monkeypatch):
    """Stopped at round 1: the NeRF is the pre-fit's again and the network's weights are
    those it started the rounds with."""
    seen: list[dict[str, torch.Tensor]] = []
    networks: list[dict[str, torch.Tensor]] = []

    def renders(nerf, scene, color=True):
        seen.append(_state_dict(nerf))
        return render_pairs(nerf, scene, color)

    original = finetune.make_pseudo_labels

    def pseudo_labels(model, scene, budget, device=None, on_progress=None, color=True):
        nerf, pseudo = original(model, scene, budget, device, on_progress, color)
        seen.append(_state_dict(nerf))  # the pre-fit NeRF, before any joint round
        networks.append({k: p.detach().clone() for k, p in model.named_parameters()})
        return nerf, pseudo

    monkeypatch.setattr("csa_core.adapt.joint.render_pairs", renders)
    monkeypatch.setattr(finetune, "make_pseudo_labels", pseudo_labels)
    force_decisions(monkeypatch, {"round 1": "stop_joint"})
    model = copy.deepcopy(pretrained)
    config = tiny_config("joint")
    result = adapt_one_step(model, target_scenes[1], config, evaluate_before=False)
    assert [d.action for d in result.decisions] == ["continue", "stop_joint"]
    prefit, trained = seen
    assert not _equal(prefit, trained)  # round 1 did train the NeRF in place ...
    assert _equal(_state_dict(result.nerf), prefit)  # ... and it was restored
    assert _equal({k: p.detach() for k, p in model.named_parameters()}, networks[0])
    assert result.trained and result.final_label_miou == result.pseudo_label_miou


@pytest.mark.parametrize("mode", ["gi_nl", "joint"])
def test_a_skipped_scene_banks_no_nerf_and_no_batchnorm_record(
    mode, pretrained, target_scenes, tmp_path, monkeypatch
):
    config = tiny_config(mode)
    model = copy.deepcopy(pretrained)
    state = ContinualState.start(config, bank=MemoryBank(tmp_path / "memory"))
    # A healthy first step fills both memories ...
    force_decisions(monkeypatch, {})
    first = continual_step(state, model, target_scenes[0])
    assert first["trained"] and state.bank.scenes == [target_scenes[0].name]
    pooled = [
        t.clone() for bn in batchnorm_layers(model) for t in (bn.running_mean, bn.running_var)
    ]
    weights = [p.detach().clone() for p in model.parameters()]
    # ... then the guard skips a scene.
    force_decisions(monkeypatch, {"prefit": "skip", "pseudo_labels": "skip"})
    record = continual_step(state, model, target_scenes[1])
    assert [d["action"] for d in record["decisions"]] == ["skip"] and not record["trained"]
    assert state.bank.scenes == [target_scenes[0].name] and record["nerf_bytes"] == 0
    assert not (tmp_path / "memory" / f"{target_scenes[1].name}.safetensors").exists()
    assert list(state.batchnorm.scenes) == [target_scenes[0].name]
    assert record["batchnorm_pooled"] == [target_scenes[0].name]
    # The network is the previous step's: weights and (pooled) statistics.
    assert all(torch.equal(a, b) for a, b in zip(weights, model.parameters(), strict=True))
    after = [t for bn in batchnorm_layers(model) for t in (bn.running_mean, bn.running_var)]
    assert all(torch.equal(a, b) for a, b in zip(pooled, after, strict=True))


@pytest.mark.parametrize("mode", ["gi_nl", "joint"])
def test_a_nerf_whose_labels_the_guard_rejected_is_not_banked(
    mode, pretrained, target_scenes, tmp_path, monkeypatch
):
    """A fallback to the network's predictions trains the network (its BatchNorm record is
    kept) but banks nothing: the record says so and the next step replays nothing of it."""
    config = tiny_config(mode)
    model = copy.deepcopy(pretrained)
    state = ContinualState.start(config, bank=MemoryBank(tmp_path / "memory"))
    force_decisions(
        monkeypatch, {"prefit": "fallback_predictions", "pseudo_labels": "fallback_predictions"}
    )
    first = continual_step(state, model, target_scenes[0])
    assert [d["action"] for d in first["decisions"]] == ["fallback_predictions"]
    assert first["trained"] and not first["nerf_banked"] and first["nerf_bytes"] == 0
    assert "replay nothing" in first["not_banked"] and "rejected" in first["not_banked"]
    assert state.bank.scenes == [] and list(state.batchnorm.scenes) == [target_scenes[0].name]
    force_decisions(monkeypatch, {})
    second = continual_step(state, model, target_scenes[1])
    assert second["replay"] == {} and second["nerf_banked"] and "not_banked" not in second
    assert state.bank.scenes == [target_scenes[1].name]


def _spy_colour(monkeypatch, force: bool | None = None) -> list[tuple[str, bool]]:
    """Record the ``color`` of every pseudo-label render of a step (the pre-fit's and each
    joint round's); ``force`` renders with that value instead."""
    calls: list[tuple[str, bool]] = []
    original = finetune.make_pseudo_labels

    def pseudo_labels(model, scene, budget, device=None, on_progress=None, color=True):
        calls.append(("prefit", color))
        return original(
            model, scene, budget, device, on_progress, color if force is None else force
        )

    def renders(nerf, scene, color=True):
        calls.append(("round", color))
        return render_pairs(nerf, scene, color if force is None else force)

    monkeypatch.setattr(finetune, "make_pseudo_labels", pseudo_labels)
    monkeypatch.setattr("csa_core.adapt.joint.render_pairs", renders)
    return calls


def test_joint_training_on_camera_images_renders_labels_only(
    pretrained, target_scenes, monkeypatch
):
    """With ``joint.render_images=False`` (the ``cpu`` preset) no NeRF image is rendered, and
    rendering them anyway changes nothing: the same network weights and label scores."""
    config = tiny_config("joint")
    config.joint.render_images = False
    assert not config.trains_on_rendered_images
    scene = target_scenes[0]
    calls = _spy_colour(monkeypatch)
    lean = copy.deepcopy(pretrained)
    result = adapt_one_step(lean, scene, config, evaluate_before=False)
    assert calls == [("prefit", False)] + [("round", False)] * config.joint.rounds
    assert [d.action for d in result.decisions] == ["continue"] * (1 + config.joint.rounds)

    monkeypatch.undo()
    _spy_colour(monkeypatch, force=True)
    full = copy.deepcopy(pretrained)
    forced = adapt_one_step(full, scene, config, evaluate_before=False)
    assert _equal(_state_dict(lean), _state_dict(full))
    assert result.final_label_miou == forced.final_label_miou
    assert result.after == forced.after


def test_joint_training_on_renders_skips_the_last_rounds_images(
    pretrained, target_scenes, monkeypatch
):
    """With rendered images (``tiny``, ``paper``) the pre-fit and every round but the last
    render images; the last round's labels only feed the guard and the score."""
    config = tiny_config("joint")
    assert config.joint.render_images and config.trains_on_rendered_images
    calls = _spy_colour(monkeypatch)
    adapt_one_step(copy.deepcopy(pretrained), target_scenes[0], config, evaluate_before=False)
    rounds = config.joint.rounds
    assert calls == [("prefit", True)] + [("round", True)] * (rounds - 1) + [("round", False)]


def test_labels_only_pseudo_labels_refuse_rendered_images(pretrained, target_scenes):
    from csa_core.adapt.pseudo_labels import make_pseudo_labels

    scene = target_scenes[1]
    _, lean = make_pseudo_labels(pretrained, scene, tiny_config().nerf, color=False)
    assert lean.rendered == {} and lean.labels.keys() == set(lean.names)
    assert len(lean.images(False)) == len(lean.names)
    with pytest.raises(ValueError, match="not rendered"):
        lean.images(True)
