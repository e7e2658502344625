"""Joint 2D-3D training (docs/method.md "Adapt"; paper Tab. 2).

A NeRF pre-fit on the network's predictions, then mutual supervision: the network trains on
labels (and, by default, images) rendered by the NeRF, and the NeRF keeps training on the
network's labels of the camera images. Two schedules (``JointBudget.schedule``):

- ``batch``, the paper's: before every network batch the NeRF renders the batch's
  current-scene views (the batch's targets) and takes one full step (colour, depth and
  semantic losses) per such view on the network's labels of it, predicted on the camera
  images with the batch's own BatchNorm statistics as the official code does. Over an epoch
  the NeRF so takes one step per training view: 10 pre-fit + 50 joint epochs equal the 60
  epochs of the fine-tuning modes' fit.
- ``round``, ours: the network trains ``seg_epochs_per_round`` epochs on the NeRF's renders;
  the network (after AdaBN on the camera images when ``AdaptConfig.adabn_before_labels``)
  labels the training frames again; the NeRF takes its round of steps on those labels and
  renders the next round's targets. On a CPU this renders the views once per round instead
  of once per epoch.

After every round (every epoch of the per-batch schedule) the NeRF's labels are checked for
collapse when the guard is enabled; a collapsed round is undone, for the network and for the
NeRF (which trained in place on the rejected round's labels), and the joint updates stop
(the guard's decision is logged and returned).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence

import numpy as np
import torch

from csa_core.adapt.config import AdaptConfig
from csa_core.adapt.finetune import (
    PSEUDO_LABELS_DONE,
    TRAINING_DONE,
    OneStepResult,
    SegFinetuner,
    adabn_slice,
    apply_adabn,
    batches_per_epoch,
    begin_step,
    check_labels,
    evaluate,
    finetune_on_labels,
    training_pairs,
)
from csa_core.adapt.nerf_training import NerfLabelTrainer
from csa_core.adapt.pseudo_labels import (
    PseudoLabels,
    label_miou,
    predict_frames,
    render_at_frames,
    render_pairs,
)
from csa_core.adapt.replay import PretrainReplay, ReplayBuffer
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.device import resolve_device
from csa_core.nerf.model import SemanticNerf
from csa_core.progress import ProgressCallback, notify, sub_progress
from csa_core.seg.adabn import batchnorm_layers
from csa_core.seg.models import SegmentationNet
from csa_core.seg.transforms import image_to_tensor, to_float_image


def joint_adapt(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    replay: ReplayBuffer | None = None,
    pretrain: PretrainReplay | None = None,
    prior_entropy: float | None = None,
    evaluate_before: bool = True,
    on_progress: ProgressCallback | None = None,
) -> OneStepResult:
    """Adapt ``model`` in place to ``scene`` by joint training; see the module docstring.
    ``on_progress`` is :func:`~csa_core.adapt.modes.adapt_one_step`'s: the pre-fit's NeRF
    steps, then every round or epoch (or every epoch of the fallback fine-tuning), then the end."""
    device = config.seg.device
    result, pseudo, seconds = begin_step(
        model, scene, config, "prefit", prior_entropy, evaluate_before, on_progress, pretrain
    )
    training_progress = sub_progress(on_progress, PSEUDO_LABELS_DONE, TRAINING_DONE)
    result.mode = "joint"
    seconds.update(joint_seg=0.0, joint_nerf=0.0, joint_render=0.0)
    decision = result.decisions[0]
    camera = pseudo.images(False)
    rendered_training = False
    if decision.action == "skip":
        result.trained = False
    elif decision.action == "fallback_predictions":
        t = time.perf_counter()
        labels = [pseudo.predictions[n] for n in pseudo.names]
        losses = finetune_on_labels(
            model, camera, labels, config, config.seg.epochs, replay, pretrain, training_progress
        )
        result.history = [{"epoch": k + 1, "loss": loss} for k, loss in enumerate(losses)]
        seconds["joint_seg"] += time.perf_counter() - t
    else:
        rendered_training = config.trains_on_rendered_images
        schedule = _per_batch if config.joint.schedule == "batch" else _per_round
        schedule(
            model,
            scene,
            config,
            result,
            pseudo,
            replay,
            pretrain,
            prior_entropy,
            seconds,
            training_progress,
        )
    if result.trained and config.adabn_after_training(rendered_training):
        apply_adabn(model, camera, adabn_slice(config, pretrain), config.seg.seed, device)
    t = time.perf_counter()
    result.after = evaluate(model, scene, device)
    seconds["evaluate"] += time.perf_counter() - t
    result.seconds = seconds
    notify(on_progress, f"adapted to {scene.name}", 1.0)
    return result


def _per_round(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    result: OneStepResult,
    pseudo: PseudoLabels,
    replay: ReplayBuffer | None,
    pretrain: PretrainReplay | None,
    prior_entropy: float | None,
    seconds: dict[str, float],
    progress: ProgressCallback | None,
) -> None:
    """Rounds of network epochs on the NeRF's renders, then NeRF steps on fresh labels."""
    device = config.seg.device
    nerf = _nerf(result)
    camera = pseudo.images(False)
    rounds, per_round = config.joint.rounds, config.joint.seg_epochs_per_round
    primary = len(pseudo.names) + (len(replay) if replay is not None else 0)
    secondary = len(pretrain) if pretrain is not None else 0
    tuner = SegFinetuner(
        model, config, rounds * per_round, batches_per_epoch(primary, secondary, config)
    )
    nerf_trainer = NerfLabelTrainer(nerf, scene, seed=config.nerf.seed)
    rendered, labels = pseudo.rendered, pseudo.labels
    for r in range(1, rounds + 1):
        kept = copy.deepcopy(model.state_dict())
        kept_nerf = {k: v.detach().clone() for k, v in nerf.state_dict().items()}
        kept_labels = labels
        t = time.perf_counter()
        images = [
            rendered[n] if config.joint.render_images else pseudo.camera[n] for n in pseudo.names
        ]
        dataset, primary, secondary = training_pairs(
            images, [labels[n] for n in pseudo.names], replay, pretrain, config.seg.augment
        )
        loss = sum(tuner.epoch(dataset, primary, secondary) for _ in range(per_round)) / per_round
        notify(progress, f"joint round {r}/{rounds}: network trained", (r - 0.6) / rounds)
        if config.adabn_before_labels:
            apply_adabn(model, camera, adabn_slice(config, pretrain), config.seg.seed, device)
        fresh = predict_frames(model, scene.train_frames, device=device)
        t_nerf = time.perf_counter()
        seconds["joint_seg"] += t_nerf - t
        nerf_trainer.set_labels(fresh)
        nerf_trainer.train(config.nerf.geometry_steps_per_round)
        nerf_trainer.train_semantics(config.nerf.steps_per_round)
        notify(progress, f"joint round {r}/{rounds}: NeRF trained", (r - 0.4) / rounds)
        t_render = time.perf_counter()
        seconds["joint_nerf"] += t_render - t_nerf
        # Images only where the next round trains on them; labels are the same either way.
        color = config.joint.render_images and r < rounds
        rendered, labels = render_pairs(nerf, scene, color=color)
        seconds["joint_render"] += time.perf_counter() - t_render
        result.history.append(
            {
                "round": r,
                "loss": loss,
                "network_label_miou": label_miou(fresh, scene),
                "nerf_label_miou": label_miou(labels, scene),
            }
        )
        decision = check_labels(f"round {r}", labels, pseudo, config, prior_entropy, in_joint=True)
        result.decisions.append(decision)
        notify(progress, f"joint round {r}/{rounds}  loss {loss:.4f}", r / rounds)
        if decision.action == "stop_joint":
            model.load_state_dict(kept)
            nerf.load_state_dict(kept_nerf)
            labels = kept_labels  # what the restored NeRF renders
            break
    result.nerf_steps["joint"] = nerf_trainer.steps_done
    result.final_label_miou = label_miou(labels, scene)


def _per_batch(
    model: SegmentationNet,
    scene: Scene,
    config: AdaptConfig,
    result: OneStepResult,
    pseudo: PseudoLabels,
    replay: ReplayBuffer | None,
    pretrain: PretrainReplay | None,
    prior_entropy: float | None,
    seconds: dict[str, float],
    progress: ProgressCallback | None,
) -> None:
    """Network epochs whose every batch is preceded by the NeRF rendering the batch's
    current-scene views and one full NeRF step per such view (the paper's schedule).

    The NeRF's semantic targets are each training view's latest network labels (the
    pre-fit's predictions until the view's first batch); its rays are drawn from all
    training views, not only the batch's."""
    device = config.seg.device
    nerf = _nerf(result)
    frames = scene.train_frames
    n = len(frames)
    epochs = config.joint.epochs
    render_images = config.joint.render_images
    dataset, primary, secondary = training_pairs(
        [pseudo.rendered[f.name] if render_images else f.color for f in frames],
        [pseudo.labels[f.name] for f in frames],
        replay,
        pretrain,
        config.seg.augment,
    )
    tuner = SegFinetuner(model, config, epochs, batches_per_epoch(primary, secondary, config))
    nerf_trainer = NerfLabelTrainer(nerf, scene, seed=config.nerf.seed)
    targets = dict(pseudo.predictions)  # the NeRF's semantic targets, refreshed per batch
    nerf_labels = dict(pseudo.labels)  # the NeRF's labels of each view, as last rendered
    guarded = config.collapse.enabled
    for e in range(1, epochs + 1):
        if guarded:
            kept = copy.deepcopy(model.state_dict())
            kept_nerf = {k: v.detach().clone() for k, v in nerf.state_dict().items()}
            kept_labels = dict(nerf_labels)
        steps_before = nerf_trainer.steps_done
        losses = []
        for batch in tuner.batches(primary, secondary):
            current = [i for i in batch if i < n]
            if current:
                views = [frames[i] for i in current]
                t = time.perf_counter()
                images, labels = render_at_frames(
                    nerf, views, scene.intrinsics, color=render_images
                )
                for i, f in zip(current, views, strict=True):
                    dataset.images[i] = images[f.name] if render_images else f.color
                    dataset.labels[i] = nerf_labels[f.name] = labels[f.name]
                t_nerf = time.perf_counter()
                seconds["joint_render"] += t_nerf - t
                targets.update(predict_with_batch_statistics(model, views, device))
                nerf_trainer.set_labels(targets)
                nerf_trainer.train(len(current))
                seconds["joint_nerf"] += time.perf_counter() - t_nerf
            t = time.perf_counter()
            losses.append(tuner.step(dataset, batch))
            seconds["joint_seg"] += time.perf_counter() - t
        tuner.end_epoch()
        loss = float(np.mean(losses)) if losses else float("nan")
        result.history.append(
            {
                "epoch": e,
                "loss": loss,
                "nerf_steps": nerf_trainer.steps_done - steps_before,
                "network_label_miou": label_miou(targets, scene),
                "nerf_label_miou": label_miou(nerf_labels, scene),
            }
        )
        notify(progress, f"joint epoch {e}/{epochs}  loss {loss:.4f}", e / epochs)
        if guarded:
            decision = check_labels(
                f"epoch {e}", nerf_labels, pseudo, config, prior_entropy, in_joint=True
            )
            result.decisions.append(decision)
            if decision.action == "stop_joint":
                model.load_state_dict(kept)
                nerf.load_state_dict(kept_nerf)
                nerf_labels = kept_labels
                break
    result.nerf_steps["joint"] = nerf_trainer.steps_done
    if any(NYU40_FOLDER in f.labels for f in frames):  # scored only where there is ground truth
        t = time.perf_counter()
        _, final = render_pairs(nerf, scene, color=False)
        seconds["joint_render"] += time.perf_counter() - t
        result.final_label_miou = label_miou(final, scene)
    else:
        result.final_label_miou = label_miou(nerf_labels, scene)


def _nerf(result: OneStepResult) -> SemanticNerf:
    if result.nerf is None:
        raise ValueError(f"joint training of {result.scene}: the step has no NeRF")
    return result.nerf


@torch.no_grad()
def predict_with_batch_statistics(
    model: SegmentationNet, frames: Sequence[Frame], device: str | None = None
) -> dict[str, np.ndarray]:
    """``{frame name: NYU40 map}`` of the network on the frames' camera images as one batch,
    its BatchNorm layers normalising with the batch's own statistics (and updating their
    running averages), as the official joint training labels the NeRF's targets. A single
    frame is predicted in eval mode (one image has no batch statistics)."""
    if len(frames) < 2:
        return predict_frames(model, frames, device=device)
    dev = resolve_device(device)
    modes = {m: m.training for m in model.modules()}
    model.to(dev).eval()
    for bn in batchnorm_layers(model):
        bn.train()
    try:
        x = to_float_image(torch.stack([image_to_tensor(f.color) for f in frames])).to(dev)
        labels = (model(x).argmax(dim=1) + 1).to(torch.uint8).cpu().numpy()
    finally:
        for m, training in modes.items():
            m.train(training)
    return {f.name: lab for f, lab in zip(frames, labels, strict=True)}
