"""Pseudo-labels of a new scene: predict with the current network, fuse in a Semantic-NeRF,
render labels (and images) back at the training views (docs/method.md "Predict", "Fuse in 3D",
"Render pseudo-labels")."""

from __future__ import annotations

import copy
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from torch import nn

from csa_core.adapt.config import NerfBudget, nerf_config
from csa_core.data.camera import Intrinsics
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.eval.miou import ConfusionMatrix
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.model import SemanticNerf
from csa_core.nerf.render import render_frames
from csa_core.progress import ProgressCallback, notify, sub_progress
from csa_core.seg.predict import predict_labels

PREDICTION_FOLDER = "prediction"


def predict_frames(
    model: nn.Module, frames: Sequence[Frame], batch_size: int = 8, device: str | None = None
) -> dict[str, np.ndarray]:
    """``{frame name: NYU40 map}`` of the network on the frames' camera images."""
    if not frames:
        return {}
    labels = predict_labels(model, [f.color for f in frames], batch_size=batch_size, device=device)
    return {f.name: lab for f, lab in zip(frames, labels, strict=True)}


def with_labels(scene: Scene, folder: str, labels: Mapping[str, np.ndarray]) -> Scene:
    """A copy of ``scene`` whose frames named in ``labels`` carry them under ``folder``
    (images are shared, the input scene is not modified)."""
    frames = []
    for f in scene.frames:
        g = copy.copy(f)
        g.labels = dict(f.labels)
        if f.name in labels:
            g.labels[folder] = labels[f.name]
        frames.append(g)
    out = copy.copy(scene)
    out.frames = frames
    return out


@dataclass
class PseudoLabels:
    """Training pairs of one scene made without its labels.

    ``camera``: the camera images; ``rendered``: the NeRF's images at the same poses;
    ``labels``: the NeRF's labels there; ``predictions``: the network's labels on the camera
    images (what the NeRF was fitted to). All keyed by frame name, in ``names`` order.
    """

    names: list[str]
    camera: dict[str, np.ndarray]
    rendered: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]
    predictions: dict[str, np.ndarray]
    seconds: dict[str, float] = field(default_factory=dict)

    def images(self, rendered: bool) -> list[np.ndarray]:
        if rendered and not self.rendered:
            raise ValueError(
                "PseudoLabels: the NeRF's images were not rendered (labels only, because the "
                "config trains on camera images: AdaptConfig.trains_on_rendered_images)"
            )
        source = self.rendered if rendered else self.camera
        return [source[n] for n in self.names]

    def label_list(self) -> list[np.ndarray]:
        return [self.labels[n] for n in self.names]


def label_miou(
    labels: Mapping[str, np.ndarray], scene: Scene, label_folder: str = NYU40_FOLDER
) -> float:
    """mIoU of label maps against the scene's ground truth (evaluation only, never training)."""
    matrix = ConfusionMatrix()
    for f in scene.frames:
        if f.name in labels and label_folder in f.labels:
            matrix.update(labels[f.name], f.labels[label_folder])
    return matrix.miou()


def render_at_frames(
    nerf: SemanticNerf, frames: Sequence[Frame], intrinsics: Intrinsics, color: bool = True
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """NeRF images and labels at the frames' poses, several views per forward pass.

    The frames' sensor depth goes along: where the NeRF's config renders views with depth
    depth-guided (``SamplerConfig.render_depth_guided``, the fast preset), samples are placed
    in the band around it instead of marching the whole ray (rays without depth still march);
    the reference preset renders with its own sampler. ``color=False`` renders labels only
    (the images dict is then empty), which keeps views with depth in the band alone.
    """
    views = render_frames(
        nerf,
        [(f.name, f.pose) for f in frames],
        intrinsics,
        depths=[f.depth for f in frames],
        color=color,
    )
    images = {v.name: v.color for v in views if v.color is not None}
    labels = {v.name: v.labels for v in views}
    return images, labels


def render_pairs(
    nerf: SemanticNerf, scene: Scene, color: bool = True
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """NeRF images and labels at the scene's training views (``color=False``: labels only,
    the images dict empty; the labels are the same either way, at about half the time on
    views with depth: benchmarks/results/speed.md "Label fusion speed and quality")."""
    return render_at_frames(nerf, scene.train_frames, scene.intrinsics, color=color)


def make_pseudo_labels(
    model: nn.Module,
    scene: Scene,
    budget: NerfBudget,
    device: str | None = None,
    on_progress: ProgressCallback | None = None,
    color: bool = True,
) -> tuple[SemanticNerf, PseudoLabels]:
    """Predict the training frames, fit a NeRF to the predictions, render labels and images
    (``color=False``: labels only, ``PseudoLabels.rendered`` empty; for a step that trains
    the network on camera images).

    ``on_progress`` (:mod:`csa_core.progress`) hears the NeRF fit's steps (most of the time)
    and the end of the semantic steps and of the rendering."""
    frames = scene.train_frames
    t0 = time.perf_counter()
    predictions = predict_frames(model, frames, device=device)
    t1 = time.perf_counter()
    labelled = with_labels(scene, PREDICTION_FOLDER, predictions)
    nerf, _ = fit_semantic_nerf(
        labelled,
        PREDICTION_FOLDER,
        nerf_config(budget),
        device=device,
        progress=False,
        on_progress=sub_progress(on_progress, 0.0, 0.8),
    )
    notify(on_progress, f"NeRF semantic steps ({nerf.config.optim.semantic_steps})", 0.9)
    t2 = time.perf_counter()
    rendered, labels = render_pairs(nerf, scene, color=color)
    t3 = time.perf_counter()
    notify(on_progress, f"rendered pseudo-labels of {len(frames)} views", 1.0)
    pseudo = PseudoLabels(
        names=[f.name for f in frames],
        camera={f.name: f.color for f in frames},
        rendered=rendered,
        labels=labels,
        predictions=predictions,
        seconds={"predict": t1 - t0, "nerf_fit": t2 - t1, "render": t3 - t2},
    )
    return nerf, pseudo
