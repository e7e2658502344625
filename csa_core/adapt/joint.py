"""Joint 2D-3D training (DESIGN.md "The method" step 4; paper Tab. 2).

A short NeRF pre-fit on the network's predictions, then rounds of mutual supervision: the
network trains for an epoch on labels (and, by default, images) rendered by the NeRF; the
network, its BatchNorm statistics re-estimated on the camera images, labels the training
frames again; the NeRF keeps training on those fresh labels and renders the next round's
targets. After every round the rendered labels are checked for collapse; a collapsed round
is undone and the joint updates stop (the guard's decision is logged and returned).
"""

from __future__ import annotations

import copy
import time

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
    label_miou,
    predict_frames,
    render_pairs,
)
from csa_core.adapt.replay import PretrainReplay, ReplayBuffer
from csa_core.data.scene import Scene
from csa_core.progress import ProgressCallback, notify, sub_progress
from csa_core.seg.models import SegmentationNet


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
    ``on_progress`` is :func:`~csa_core.adapt.finetune.adapt_one_step`'s: the pre-fit's NeRF
    steps, then every round (or every epoch of the fallback fine-tuning), then the end."""
    device = config.seg.device
    result, pseudo, seconds = begin_step(
        model, scene, config, "prefit", prior_entropy, evaluate_before, on_progress, pretrain
    )
    training_progress = sub_progress(on_progress, PSEUDO_LABELS_DONE, TRAINING_DONE)
    result.mode = "joint"
    seconds.update(joint_seg=0.0, joint_nerf=0.0, joint_render=0.0)
    decision = result.decisions[0]
    nerf = result.nerf
    camera = pseudo.images(False)
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
        rounds, per_round = config.joint.rounds, config.joint.seg_epochs_per_round
        primary = len(pseudo.names) + (len(replay) if replay is not None else 0)
        secondary = len(pretrain) if pretrain is not None else 0
        tuner = SegFinetuner(
            model, config, rounds * per_round, batches_per_epoch(primary, secondary, config)
        )
        nerf_trainer = NerfLabelTrainer(
            nerf, scene, rays_per_step=config.nerf.rays_per_step, seed=config.nerf.seed
        )
        rendered, labels = pseudo.rendered, pseudo.labels
        for r in range(1, rounds + 1):
            kept = copy.deepcopy(model.state_dict())
            t = time.perf_counter()
            images = [
                rendered[n] if config.joint.render_images else pseudo.camera[n]
                for n in pseudo.names
            ]
            dataset, primary, secondary = training_pairs(
                images, [labels[n] for n in pseudo.names], replay, pretrain
            )
            loss = (
                sum(tuner.epoch(dataset, primary, secondary) for _ in range(per_round)) / per_round
            )
            notify(training_progress, f"joint round {r}/{rounds}: network trained", (r - 0.6) / rounds)
            apply_adabn(model, camera, adabn_slice(config, pretrain), config.seg.seed, device)
            fresh = predict_frames(model, scene.train_frames, device=device)
            t_nerf = time.perf_counter()
            seconds["joint_seg"] += t_nerf - t
            nerf_trainer.set_labels(fresh)
            nerf_trainer.train(config.nerf.geometry_steps_per_round)
            nerf_trainer.train_semantics(config.nerf.steps_per_round)
            notify(training_progress, f"joint round {r}/{rounds}: NeRF trained", (r - 0.4) / rounds)
            t_render = time.perf_counter()
            seconds["joint_nerf"] += t_render - t_nerf
            rendered, labels = render_pairs(nerf, scene)
            seconds["joint_render"] += time.perf_counter() - t_render
            entry = {
                "round": r,
                "loss": loss,
                "network_label_miou": label_miou(fresh, scene),
                "nerf_label_miou": label_miou(labels, scene),
            }
            result.history.append(entry)
            decision = check_labels(
                f"round {r}", labels, pseudo, config, prior_entropy, in_joint=True
            )
            result.decisions.append(decision)
            notify(training_progress, f"joint round {r}/{rounds}  loss {loss:.4f}", r / rounds)
            if decision.action == "stop_joint":
                model.load_state_dict(kept)
                break
        result.final_label_miou = label_miou(labels, scene)
    if config.adabn and result.trained:
        apply_adabn(model, camera, adabn_slice(config, pretrain), config.seg.seed, device)
    t = time.perf_counter()
    result.after = evaluate(model, scene, device)
    seconds["evaluate"] += time.perf_counter() - t
    result.seconds = seconds
    notify(on_progress, f"adapted to {scene.name}", 1.0)
    return result
