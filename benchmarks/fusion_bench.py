"""Label fusion side by side: the voxel map (the Mapping baseline's fusion) against each NeRF
preset, on the same frames and labels, in one run. Prints one Markdown table (not a test).

Examples (run from the repository root):

    python benchmarks/fusion_bench.py --families all --variants clean,hard --frames 250
    python benchmarks/fusion_bench.py synth:office:0 --variants hard --presets fast --steps 300
    python benchmarks/fusion_bench.py synth:office:0 --variants hard --renders holes-marched
    python benchmarks/fusion_bench.py folder:data/office_0 --labels label-noisy
    python benchmarks/fusion_bench.py synth:studio:1 --predictions model.safetensors
    python benchmarks/fusion_bench.py ../shared/data/7scenes-kitchen-100 --frames 100
    python benchmarks/fusion_bench.py ../shared/data/7scenes-kitchen-100 --frames 100 \
        --space-labels --variants clean,hard --presets none

Scenes: ``synth:FAMILY:SEED`` (rendered in memory), ``folder:PATH`` or a bare path to a scene
folder, and a 7-Scenes sequence folder (bare path or ``7scenes:PATH``), imported with the
project's importer at ``--size`` and moved to the Kinect colour camera. ``--families`` adds
``synth:FAMILY:SEED`` for each family (``all``: every family of ``csa data families``).
``--capture random`` renders the synthetic rooms from viewpoints spread at random through the
room instead of the walk (``csa data synth --capture``); the scene is named ``FAMILY_SEED_random``.

Labels fused (training views; ground truth ``label-nyu40`` scores them):
``--noise`` (default for scenes with ground truth) corrupts each frame's ground truth
(``csa_core.data.label_noise``); ``--labels NAME`` takes a label folder of the scene;
``--predictions MODEL.safetensors`` takes a segmentation network's predictions.
``--variants hard`` turns each scene into a Kinect-like capture first
(``csa_core.data.synth.kinect``): noisy depth with holes and noisy colour, and with ``--noise``
labels with systematic (view-consistent) errors besides the per-frame ones; with
``--labels``/``--predictions`` the labels stay as given (predictions are made on the degraded
colour). ``--variants outliers`` keeps the clean scene and its labels but makes 3% of each
frame's measured depth pixels read 20-60 m (far outliers, as multipath or sunlight give a
depth sensor), to see what they cost each fuser. ``--variants flying`` keeps the clean scene and
its labels but gives half of the pixels on either side of every depth jump a depth between the
two surfaces (the flying pixels of a time-of-flight sensor, ``mix_depth_edges``). Scenes without labels (7-Scenes) get colour
and depth quality instead: the NeRF's
held-out PSNR and depth L1 (rendered without the view's depth) against the map's depth L1 and
coverage (share of held-out pixels whose ray meets the map).

``--space-labels`` gives scenes without labels (7-Scenes, a scene folder without
``label-nyu40``) ground truth defined in 3D on their own geometry
(``csa_core.data.space_labels``, seeded with ``--seed``): floor, ceiling and walls found as
planes in the fused depth, the rest of space cut into furniture and object regions; a pixel's
label is that of the 3D point its measured depth backprojects to, 0 without depth. They are
written as the scene's ``label-nyu40`` in memory, so ``--noise`` and the label rows work as for
synthetic rooms (the printed class shares say what they contain). The labels follow space, not
real objects: they score multi-view consistency on real geometry and real depth noise, not
recognition. ``--variants hard`` then adds only the systematic and per-frame label errors: the
real sensor's colour and depth are kept as measured. ``--space-labels all`` replaces the ground
truth of labelled scenes too (synthetic rooms: to see whether fusers rank alike on space labels
and on true labels; their hard variant degrades their clean depth as usual). Only with
``--noise``.

Rows: ``input`` is the per-frame labels themselves; ``map`` fuses them in 5 cm voxels
(``build_voxel_map``) and reads each view by ray casting (``render_map_labels``, Frey et al.);
``map, depth read-back`` reads the same map through each view's own measured depth (the
older read-back: it can only label pixels with depth); one row per NeRF preset
(``fit_semantic_nerf``, rendered with ``render_views``). ``--renders`` adds rows that render
the same fit again with another render option (fit seconds and size are the fit's):
``holes-marched`` marches the pixels in depth holes along the whole ray (the render before
``SamplerConfig.render_hole_estimate``), ``unseen-unknown`` labels surfaces that no training
camera saw 0, unknown, as the map does (``NerfConfig.render_unseen_unknown``; with a preset
entry ``fast+observed_resolution=128``, the cells its views' depth measured; its printed
line also gives ``val_unknown``, the share of held-out pixels left unknown). ``labels-at-depth`` renders one sample
per ray, at the measured (or, in holes, estimated) depth: the class the semantic field holds at
the measured surface point, the NeRF's counterpart of the map's depth read-back. ``label-sigma-0.5`` and
``label-sigma-0.25`` weight the band's samples by a Gaussian around the measured depth for
the labels (``SamplerConfig.render_band_label_sigma``). ``novel-marched``
and ``novel-estimated`` render the held-out views from their poses alone (novel views: colour
and labels, no depth), every ray marched or rendered around its estimated surface
(``SamplerConfig.render_novel_estimate``); they give val mIoU, val PSNR and seconds per
held-out view. ``novel-fine-march`` marches them as before the preset's coarser render march
(``SamplerConfig.render_march_steps``, ``render_early_stop``, ``render_min_weight``): at the
grid's step, to transmittance 1/1000. Columns: mIoU on
the training views and on the held-out views (the scene's last 20%), fit seconds, render seconds per view (train
and held-out views together), stored bytes (map: keys and scores as held in memory; NeRF: its
checkpoint file) and peak memory: the process's peak resident set size while that fuser fit
and rendered (Linux: VmHWM, reset before each fuser through /proc/self/clear_refs; elsewhere
``resource.getrusage``, the peak since the process started). It includes the interpreter,
the libraries and the scene in memory; ``RSS before`` is the resident size when the fuser
started. ``--per-class`` also prints, per scene and variant, every fuser's IoU of each class
present (train / val views); ``--json`` always holds them.
"""

from __future__ import annotations

import argparse
import copy
import json
import platform
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from nerf_bench import color_camera, image_mse, load_scene, psnr

from csa_core.adapt.baselines.mapping import build_voxel_map, render_map_labels
from csa_core.adapt.baselines.voxel_map import VoxelMapConfig
from csa_core.atomic_io import write_text_atomic
from csa_core.data.label_noise import corrupt_labels
from csa_core.data.nyu40 import CLASS_NAMES
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.data.space_labels import add_space_labels, label_shares
from csa_core.data.synth import (
    NOISY_FOLDER,
    degrade_scene,
    family_names,
    generate_scene,
    mix_depth_edges,
    parse_size,
)
from csa_core.data.synth.camera_path import CAPTURES
from csa_core.errors import CSAInputError
from csa_core.eval import ConfusionMatrix
from csa_core.nerf import (
    NerfConfig,
    fit_semantic_nerf,
    preset,
    render_frames,
    render_image,
    render_views,
    save_checkpoint,
)
from csa_core.overrides import apply_overrides

INPUT = "input"  # label folder the fusers read in this benchmark


# ---- peak memory -----------------------------------------------------------------------


def _status_kb(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss() -> str:
    """Reset the peak-RSS counter where the OS allows it; returns how peaks are measured."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return "VmHWM"
    except OSError:
        return "ru_maxrss"


def peak_rss_mb(how: str) -> float:
    if how == "VmHWM":
        kb = _status_kb("VmHWM")
        if kb is not None:
            return kb / 1024
    scale = 1 if sys.platform == "darwin" else 1024  # bytes on macOS, kB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale / 2**20


# ---- scenes and labels -----------------------------------------------------------------


def scene_specs(args: argparse.Namespace) -> list[str]:
    specs = list(args.scenes)
    if args.families:
        names = family_names() if args.families == "all" else args.families.split(",")
        specs += [f"synth:{name}:{args.seed}" for name in names]
    if not specs:
        raise SystemExit("give scene(s) or --families (see --help)")
    return specs


def open_scene(spec: str, size: tuple[int, int], frames: int, capture: str = "walk") -> tuple[Scene, bool]:
    """A scene and whether it has ground-truth labels. A bare path is a 7-Scenes sequence
    (frame-XXXXXX.color.*) or a scene folder; ``capture`` is the synthetic rooms' capture mode."""
    if spec.startswith("synth:") and capture != "walk":
        family, _, seed = spec.removeprefix("synth:").partition(":")
        family, seed = family or "apartment", int(seed or 0)
        return generate_scene(family, seed, frames, size, f"{family}_{seed}_{capture}", capture), True
    if ":" not in spec.split("/")[0]:
        path = Path(spec)
        seven = path.is_dir() and any(path.glob("frame-*.color.*"))
        spec = f"7scenes:{spec}" if seven else f"folder:{spec}"
    scene, labelled = load_scene(spec, size, frames)
    if spec.startswith("7scenes:"):
        scene, _ = color_camera(scene, "kinect")
        scene.frames = scene.frames[:frames]
        labelled = False
    elif spec.startswith("folder:"):
        scene.frames = scene.frames[:frames]
        labelled = all(NYU40_FOLDER in f.labels for f in scene.frames)
    return scene, labelled


def wants_space_labels(labelled: bool, args: argparse.Namespace) -> bool:
    """Whether ``--space-labels`` gives this scene its ground truth."""
    return args.space_labels == "all" or (args.space_labels == "missing" and not labelled)


def give_space_labels(scene: Scene, args: argparse.Namespace) -> str:
    """Write the scene's space labels as its ground truth ``label-nyu40`` (in place); returns
    their class shares as one printable line."""
    add_space_labels(scene, args.seed)
    shares = sorted(label_shares(scene).items(), key=lambda kv: -kv[1])
    return ", ".join(f"{CLASS_NAMES[c]} {100 * v:.2f}%" for c, v in shares)


def prepare(
    scene: Scene,
    labelled: bool,
    variant: str,
    args: argparse.Namespace,
    keep_sensor: bool = False,
) -> str | None:
    """Make the ``variant`` of ``scene`` in place and put the labels to fuse under ``INPUT``;
    returns what they are (``None``: no labels). ``keep_sensor``: a real capture, whose hard
    variant keeps its measured colour and depth and gets only the label errors."""
    if variant == "outliers":  # depth only: the labels below are made as for ``clean``
        add_far_outliers(scene, np.random.default_rng([args.seed, 1]))
    if variant == "flying":  # depth only, as ``outliers``
        rng = np.random.default_rng([args.seed, 2])
        for f in scene.frames:
            if f.depth is not None:
                f.depth = mix_depth_edges(f.depth, rng, FLYING_SHARE)
    source = "predictions" if args.predictions else f"folder {args.labels}" if args.labels else None
    if source is None and not labelled:
        return None
    simulate = source is None  # --noise
    if variant == "hard" and not (keep_sensor and not simulate):
        hard = degrade_scene(
            scene, args.seed, source=NYU40_FOLDER if simulate else None, target=NOISY_FOLDER
        )
        if keep_sensor:  # the label errors only: colour and depth stay the sensor's
            for frame, degraded in zip(scene.frames, hard.frames, strict=True):
                frame.labels[NOISY_FOLDER] = degraded.labels[NOISY_FOLDER]
        else:
            scene.frames = hard.frames
    if args.labels:
        missing = [f.name for f in scene.frames if args.labels not in f.labels]
        if missing:
            raise SystemExit(
                f"--labels {args.labels}: frame(s) {', '.join(missing[:5])} of {scene.name} have "
                f"none (label folders: {', '.join(scene.label_folders) or 'none'})"
            )
        for f in scene.frames:
            f.labels[INPUT] = f.labels[args.labels]
        return source
    if args.predictions:
        from csa_core.seg.checkpoint import load_checkpoint
        from csa_core.seg.predict import predict_scene

        model, card = load_checkpoint(args.predictions, device=args.device_torch)
        size = tuple(card.input_size) if card.input_size else None
        labels = predict_scene(model, scene, "all", device=args.device_torch, size=size)
        for f in scene.frames:
            f.labels[INPUT] = labels[f.name]
        return f"{source} of {Path(args.predictions).name}"
    if variant == "hard":
        for f in scene.frames:
            f.labels[INPUT] = f.labels[NOISY_FOLDER]
        return "systematic + per-frame errors"
    rng = np.random.default_rng(args.seed)
    for f in scene.frames:
        f.labels[INPUT] = corrupt_labels(f.labels[NYU40_FOLDER], rng)
    return "per-frame errors"


# The ``outliers`` variant: this share of each frame's measured depth pixels reads far away,
# uniformly in this range of metres (multipath and sunlight on a time-of-flight or
# structured-light sensor); colour and labels stay as in ``clean``.
OUTLIER_SHARE = 0.03
OUTLIER_RANGE = (20.0, 60.0)


# The ``flying`` variant: this share of the pixels beside every depth jump reads a depth
# between the two surfaces.
FLYING_SHARE = 0.5


def add_far_outliers(scene: Scene, rng: np.random.Generator) -> None:
    """Replace :data:`OUTLIER_SHARE` of every frame's measured depth by far readings, in place."""
    for f in scene.frames:
        if f.depth is None:
            continue
        depth = f.depth.copy()
        ys, xs = np.nonzero(depth > 0)
        pick = rng.random(ys.size) < OUTLIER_SHARE
        depth[ys[pick], xs[pick]] = rng.uniform(*OUTLIER_RANGE, int(pick.sum())).astype(depth.dtype)
        f.depth = depth


def confusion(labels: dict[str, np.ndarray], frames) -> ConfusionMatrix:
    matrix = ConfusionMatrix()
    for f in frames:
        matrix.update(labels[f.name], f.labels[NYU40_FOLDER])
    return matrix


def miou(labels: dict[str, np.ndarray], frames) -> float:
    return confusion(labels, frames).miou()


def label_scores(labels: dict[str, np.ndarray], *splits: tuple[str, Any]) -> dict[str, Any]:
    """``miou_SPLIT`` and ``class_iou_SPLIT`` (IoU per class present, by class name) of
    ``labels`` for each ``(SPLIT, frames)``."""
    out: dict[str, Any] = {}
    for split, frames in splits:
        matrix = confusion(labels, frames)
        iou = matrix.per_class_iou()
        out[f"miou_{split}"] = matrix.miou()
        out[f"class_iou_{split}"] = {
            CLASS_NAMES[c]: float(iou[c]) for c in matrix.present_classes()
        }
        gt_pixels = matrix.counts.sum(axis=1)
        out[f"class_share_{split}"] = {
            CLASS_NAMES[c]: float(gt_pixels[c] / max(1, matrix.num_pixels))
            for c in matrix.present_classes()
        }
    return out


# ---- fusers ----------------------------------------------------------------------------


def held_out_psnr(frames, colors: dict[str, np.ndarray]) -> float:
    """PSNR (dB) of rendered ``colors`` (``{frame name: (H, W, 3) uint8}``) against the
    frames' camera images, from the mean squared error over all of them."""
    return psnr(float(np.mean([image_mse(colors[f.name], f.color) for f in frames])))


def measured(fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    """Run one fuser, ``fn(*args)``; add its peak resident memory to its row."""
    how = reset_peak_rss()
    start = _status_kb("VmRSS")
    row = fn(*args)
    row["peak_rss_mb"] = peak_rss_mb(how)
    if start is not None:
        row["start_rss_mb"] = start / 1024
    row["peak_rss_how"] = how
    return row


def map_rows(scene: Scene, has_labels: bool, args: argparse.Namespace) -> list[dict[str, Any]]:
    train, val = scene.train_frames, scene.val_frames
    cfg = VoxelMapConfig(voxel_size=args.voxel)
    if has_labels:
        inputs = {f.name: f.labels[INPUT] for f in train}
    else:  # geometry only: every measured point votes for one class
        inputs = {f.name: (f.depth > 0).astype(np.uint8) for f in train}
    views = [f.name for f in scene.frames]
    out: dict[str, Any] = {}

    def fit_and_cast() -> dict[str, Any]:
        t0 = time.perf_counter()
        out["map"] = build_voxel_map(scene, inputs, cfg, args.device_torch)
        fit_s = time.perf_counter() - t0
        row = {"fuser": f"map ({100 * args.voxel:.0f} cm)", "fit_s": fit_s}
        row["stored_mb"] = out["map"].nbytes / 1e6
        t0 = time.perf_counter()
        if has_labels:
            labels = render_map_labels(out["map"], scene, views)
        else:
            cast = {f.name: out["map"].raycast(f.pose, scene.intrinsics) for f in val}
        row["render_s_per_view"] = (time.perf_counter() - t0) / (
            len(views) if has_labels else len(val)
        )
        if has_labels:
            row.update(label_scores(labels, ("train", train), ("val", val)))
        else:
            measured_px = [f.depth > 0 for f in val]
            hit = [cast[f.name][1] > 0 for f in val]
            row["val_coverage"] = float(np.mean([h.mean() for h in hit]))
            err = [
                np.abs(cast[f.name][1] - f.depth)[m & h]
                for f, m, h in zip(val, measured_px, hit, strict=True)
            ]
            row["val_depth_l1_m"] = float(np.concatenate(err).mean())
        return row

    rows = [measured(fit_and_cast)]
    if has_labels:

        def depth_read() -> dict[str, Any]:
            t0 = time.perf_counter()
            labels = render_map_labels(out["map"], scene, views, read="depth")
            row = {"fuser": "map, depth read-back", "fit_s": rows[0]["fit_s"]}
            row["render_s_per_view"] = (time.perf_counter() - t0) / len(views)
            row["stored_mb"] = rows[0]["stored_mb"]
            row.update(label_scores(labels, ("train", train), ("val", val)))
            return row

        rows.append(measured(depth_read))
    return rows


def preset_config(name: str, sets: list[str]) -> NerfConfig:
    """The NeRF config of a ``--presets`` entry ``PRESET[+KEY=VALUE...]``: the preset, then
    ``--set``, then the entry's own overrides."""
    base, *own = name.split("+")
    cfg = apply_overrides(preset(base), sets)
    return apply_overrides(cfg, own, flag=f"--presets {name}")


def nerf_row(
    scene: Scene,
    has_labels: bool,
    name: str,
    args: argparse.Namespace,
    fitted: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Fit preset ``name`` and score its renders; the model goes into ``fitted["nerf"]``."""
    train, val = scene.train_frames, scene.val_frames
    cfg = preset_config(name, args.set)
    nerf, stats = fit_semantic_nerf(
        scene,
        INPUT if has_labels else None,
        cfg,
        device=args.device,
        frames=train,
        steps=args.steps,
        progress=False,
    )
    if fitted is not None:
        fitted["nerf"] = nerf
    row: dict[str, Any] = {"fuser": f"NeRF {name} ({stats.steps} steps)", "fit_s": stats.seconds}
    with tempfile.TemporaryDirectory() as tmp:
        row["stored_mb"] = save_checkpoint(nerf, Path(tmp) / "nerf.safetensors") / 1e6
    t0 = time.perf_counter()
    if has_labels:
        rendered = {}
        for views in ("train", "val"):
            for v in render_views(nerf, scene, views, semantics=True, color=False):
                rendered[v.name] = v.labels
        row["render_s_per_view"] = (time.perf_counter() - t0) / len(scene.frames)
        row.update(label_scores(rendered, ("train", train), ("val", val)))
        return row
    # Colour and geometry at the held-out views, rendered without their measured depth.
    colors, errs = {}, []
    for f in val:
        v = render_image(nerf, f.pose, scene.intrinsics, semantics=False)
        colors[f.name] = v.color
        m = f.depth > 0
        errs.append(np.abs(v.depth[m] - f.depth[m]))
    row["render_s_per_view"] = (time.perf_counter() - t0) / len(val)
    row["val_psnr"] = held_out_psnr(val, colors)
    row["val_depth_l1_m"] = float(np.concatenate(errs).mean())
    row["val_coverage"] = 1.0
    return row


# The march of a view without depth before benchmarks/results/speed.md "A cheaper march for
# novel views": the grid's own step, stopped at transmittance 1/1000, samples of
# weight 1/10000 kept.
FINE_MARCH = [
    ("sampler", "render_march_steps", None),
    ("sampler", "render_early_stop", 1e-3),
    ("sampler", "render_min_weight", 1e-4),
]
RENDERS = {  # --renders: name -> (row suffix, render options of the fitted model, views' depth)
    "holes-marched": ("holes marched", [("sampler", "render_hole_estimate", False)], True),
    "unseen-unknown": ("unseen=unknown", [(None, "render_unseen_unknown", True)], True),
    "labels-at-depth": ("labels at the measured depth", [("sampler", "render_band_samples", 1)], True),
    "label-sigma-0.5": (
        "band labels x Gaussian, sigma 1/2 band",
        [("sampler", "render_band_label_sigma", 0.5)],
        True,
    ),
    "label-sigma-0.25": (
        "band labels x Gaussian, sigma 1/4 band",
        [("sampler", "render_band_label_sigma", 0.25)],
        True,
    ),
    "unseen-unknown+label-sigma-0.25": (
        "unseen=unknown, band labels x Gaussian, sigma 1/4 band",
        [(None, "render_unseen_unknown", True), ("sampler", "render_band_label_sigma", 0.25)],
        True,
    ),
    "novel-marched": ("held-out views without depth, marched", [], False),
    "novel-fine-march": (
        "held-out views without depth, marched at the grid's step",
        FINE_MARCH,
        False,
    ),
    "novel-estimated": (
        "held-out views without depth, surface estimated",
        [("sampler", "render_novel_estimate", True)],
        False,
    ),
}


def render_options(render: str, config: Any) -> tuple[str, list[tuple[str | None, str, Any]], bool]:
    """Row suffix, render options and whether the views' depth is used, of ``--renders`` entry
    ``render``: a name of ``RENDERS``, or config overrides joined by ``+``
    (``sampler.render_band_samples=12+sampler.render_surface_label_weight=0.5``), parsed as
    ``--set`` parses them (on a copy of ``config``) and rendered with the views' depth."""
    if render in RENDERS:
        return RENDERS[render]
    items = [item for item in render.split("+") if item]
    parsed = apply_overrides(copy.deepcopy(config), items, flag="--renders")
    options = []
    for item in items:
        key = item.partition("=")[0].strip()
        section, _, name = key.rpartition(".")
        if "." in section:
            raise CSAInputError(f"--renders {item}", "render overrides take section.key or key")
        value = getattr(parsed if not section else getattr(parsed, section), name)
        options.append((section or None, name, value))
    return " ".join(items), options, True


def render_row(
    scene: Scene, fitted: dict[str, Any], fit: dict[str, Any], render: str
) -> dict[str, Any]:
    """The labels of an already fitted NeRF (``fitted["nerf"]``, row ``fit``) rendered again
    with the ``render`` option of ``RENDERS`` switched. The ``novel-*`` rows render the held-out
    views as novel views: from their poses alone, colour and labels, as ``csa nerf render
    --views novel`` does; they score val mIoU and PSNR only."""
    nerf = fitted["nerf"]
    suffix, options, with_depth = render_options(render, nerf.config)
    saved = []
    for section, key, value in options:
        target = nerf.config if section is None else getattr(nerf.config, section)
        saved.append((target, key, getattr(target, key)))
        setattr(target, key, value)
    try:
        t0 = time.perf_counter()
        rendered, colors = {}, {}
        if with_depth:
            for views in ("train", "val"):
                for v in render_views(nerf, scene, views, semantics=True, color=False):
                    rendered[v.name] = v.labels
            n_views = len(scene.frames)
        else:
            val = scene.val_frames
            poses = [(f.name, f.pose) for f in val]
            for v in render_frames(nerf, poses, scene.intrinsics, semantics=True, color=True):
                rendered[v.name], colors[v.name] = v.labels, v.color
            n_views = len(val)
        seconds = (time.perf_counter() - t0) / n_views
    finally:
        for target, key, before in saved:
            setattr(target, key, before)
    row = {"fuser": f"{fit['fuser']}, {suffix}", "fit_s": fit["fit_s"]}
    row["render_s_per_view"] = seconds
    row["stored_mb"] = fit["stored_mb"]
    splits = [("train", scene.train_frames)] if with_depth else []
    row.update(label_scores(rendered, *splits, ("val", scene.val_frames)))
    if colors:
        row["val_psnr"] = held_out_psnr(scene.val_frames, colors)
    if any(key == "render_unseen_unknown" and value for _, key, value in options):
        row["val_unknown"] = float(
            np.mean([(rendered[f.name] == 0).mean() for f in scene.val_frames])
        )
    return row


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    for spec in scene_specs(args):
        for variant in args.variants.split(","):
            scene, labelled = open_scene(spec, args.size, args.frames, args.capture)
            space = wants_space_labels(labelled, args)
            # A real capture keeps its colour and depth in the hard variant; a synthetic room
            # (exact depth) is degraded as usual.
            keep_sensor = space and not spec.startswith("synth:")
            if space:
                shares = give_space_labels(scene, args)
                labelled = True
                print(f"{spec}: space labels (seed {args.seed}): {shares}", flush=True)
            if variant == "hard" and not labelled and not (args.labels or args.predictions):
                print(f"{spec}: no ground truth to degrade from; hard variant skipped")
                continue
            labels = prepare(scene, labelled, variant, args, keep_sensor)
            if labels is not None and space:
                labels += ", space-label ground truth"
                if variant == "hard" and keep_sensor:
                    labels += ", sensor depth kept"
            has_labels = labels is not None
            head = {"scene": scene.name, "variant": variant, "labels": labels or "no labels"}
            head["views"] = f"{scene.num_train}+{len(scene.val_frames)}"
            print(f"{spec} ({variant}): {len(scene)} frames, labels: {head['labels']}", flush=True)
            if has_labels and labelled:
                inputs = {f.name: f.labels[INPUT] for f in scene.frames}
                rows.append(
                    {
                        **head,
                        "fuser": "input (per frame)",
                        **label_scores(
                            inputs, ("train", scene.train_frames), ("val", scene.val_frames)
                        ),
                    }
                )
            scored = has_labels and labelled
            fused = map_rows(scene, scored, args)
            for name in [n for n in args.presets.split(",") if n not in ("", "none")]:
                fitted: dict[str, Any] = {}
                fit = measured(nerf_row, scene, scored, name, args, fitted)
                fused.append(fit)
                for render in args.renders if scored else []:
                    fused.append(measured(render_row, scene, fitted, fit, render))
            for row in fused:
                rows.append({**head, **row})
                shown = {k: v for k, v in row.items() if not k.startswith(("class_iou_", "class_share_"))}
                print("  " + ", ".join(f"{k} {fmt(k, v)}" for k, v in shown.items()), flush=True)
    return rows


# ---- output ----------------------------------------------------------------------------

COLUMNS = [
    ("scene", "{}"),
    ("variant", "{}"),
    ("labels", "{}"),
    ("views", "{}"),
    ("fuser", "{}"),
    ("miou_train", "{:.1%}"),
    ("miou_val", "{:.1%}"),
    ("fit_s", "{:.2f}"),
    ("render_s_per_view", "{:.3f}"),
    ("stored_mb", "{:.2f}"),
    ("peak_rss_mb", "{:.0f}"),
    ("start_rss_mb", "{:.0f}"),
    ("val_psnr", "{:.2f}"),
    ("val_depth_l1_m", "{:.3f}"),
    ("val_coverage", "{:.1%}"),
]
HEADERS = {
    "miou_train": "mIoU train views",
    "miou_val": "mIoU val views",
    "fit_s": "fit s",
    "render_s_per_view": "render s / view",
    "stored_mb": "stored MB",
    "peak_rss_mb": "peak RSS MB",
    "start_rss_mb": "RSS before MB",
    "val_psnr": "val PSNR",
    "val_depth_l1_m": "val depth L1 m",
    "val_coverage": "val coverage",
}


def fmt(key: str, value: Any) -> str:
    spec = dict(COLUMNS).get(key, "{}")
    try:
        return spec.format(value)
    except (ValueError, TypeError):
        return str(value)


def table(rows: list[dict[str, Any]]) -> str:
    cols = [c for c, _ in COLUMNS if any(c in r for r in rows)]
    lines = ["| " + " | ".join(HEADERS.get(c, c) for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            if c in r:
                cells.append(fmt(c, r[c]))
            elif c.startswith("miou") and r.get("labels") == "no labels":
                cells.append("no labels")
            else:
                cells.append("-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def class_tables(rows: list[dict[str, Any]]) -> str:
    """One table per scene and variant: IoU of each class present (rows, by name) for each
    fuser (columns), on the train / val views."""
    out = []
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        if "class_iou_val" in r:
            groups.setdefault((r["scene"], r["variant"]), []).append(r)
    for (scene, variant), group in groups.items():
        names = sorted(
            {c for r in group for c in r["class_iou_val"]}
            | {c for r in group for c in r.get("class_iou_train", {})}
        )
        out.append(f"\n{scene} ({variant}): IoU per class, train / val views")
        out.append("| class | " + " | ".join(r["fuser"] for r in group) + " |")
        out.append("|---|" + "---|" * len(group))
        for c in names:
            cells = []
            for r in group:
                t = r.get("class_iou_train", {}).get(c)
                v = r["class_iou_val"].get(c)
                cells.append(" / ".join("-" if x is None else f"{100 * x:.1f}" for x in (t, v)))
            out.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(out)


# The fusion targets (benchmarks/RESULTS.md "Targets"): the NeRF at or above the map's better
# read-back on both splits, no class of at least MIN_CLASS_SHARE of a split's pixels more
# than MAX_CLASS_GAP IoU points below it, fit plus the labels of every view within
# MAX_FIT_AND_LABELS_S, a checkpoint of at most MAX_CHECKPOINT_MB.
MIN_CLASS_SHARE = 0.01
MAX_CLASS_GAP = 0.05
MAX_FIT_AND_LABELS_S = 300.0
MAX_CHECKPOINT_MB = 5.0


def target_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """For each scene, variant and NeRF row: its mIoU margin over the map's better read-back
    (the larger of ray cast and depth read-back, per split), its worst class against the
    better read-back's IoU of that class (classes of at least ``MIN_CLASS_SHARE`` of the
    split's pixels), fit plus labels seconds, checkpoint MB, and whether all targets hold."""
    out = []
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        if "class_iou_val" in r:
            groups.setdefault((r["scene"], r["variant"]), []).append(r)
    for (scene, variant), group in groups.items():
        maps = [r for r in group if r["fuser"].startswith("map")]
        nerfs = [r for r in group if r["fuser"].startswith("NeRF")]
        if not maps:
            continue
        for nerf in nerfs:
            row: dict[str, Any] = {"scene": scene, "variant": variant, "fuser": nerf["fuser"]}
            ok = True
            for split in ("train", "val"):
                best = max(m[f"miou_{split}"] for m in maps)
                row[f"margin_{split}"] = nerf[f"miou_{split}"] - best
                ok &= row[f"margin_{split}"] >= 0
                worst, gap = "-", 0.0
                for name, share in nerf[f"class_share_{split}"].items():
                    if share < MIN_CLASS_SHARE:
                        continue
                    ref = max(m[f"class_iou_{split}"].get(name, 0.0) for m in maps)
                    g = nerf[f"class_iou_{split}"].get(name, 0.0) - ref
                    if g < gap:
                        worst, gap = name, g
                row[f"worst_class_{split}"] = f"{worst} {100 * gap:+.1f}"
                ok &= gap >= -MAX_CLASS_GAP
            views = int(sum(int(n) for n in str(group[0]["views"]).split("+")))
            row["fit_and_labels_s"] = nerf["fit_s"] + nerf["render_s_per_view"] * views
            row["stored_mb"] = nerf["stored_mb"]
            ok &= row["fit_and_labels_s"] <= MAX_FIT_AND_LABELS_S
            ok &= row["stored_mb"] <= MAX_CHECKPOINT_MB
            row["targets"] = "met" if ok else "missed"
            out.append(row)
    return out


def targets_table(rows: list[dict[str, Any]]) -> str:
    """The targets of every NeRF row (:func:`target_rows`) as one Markdown table."""
    lines = [
        "| scene | variant | fuser | vs better read-back, train | val | worst class, train "
        "| val | fit + labels s | MB | targets |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in target_rows(rows):
        lines.append(
            f"| {r['scene']} | {r['variant']} | {r['fuser']} | {100 * r['margin_train']:+.1f} "
            f"| {100 * r['margin_val']:+.1f} | {r['worst_class_train']} | {r['worst_class_val']} "
            f"| {r['fit_and_labels_s']:.0f} | {r['stored_mb']:.2f} | {r['targets']} |"
        )
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "scenes", nargs="*", help="synth:FAMILY:SEED, folder:PATH, 7scenes:PATH or a path"
    )
    p.add_argument("--families", default=None, help="'all' or comma-separated synthetic families")
    p.add_argument("--seed", type=int, default=0, help="room seed of --families, noise seed")
    p.add_argument("--frames", type=int, default=250, help="frames per scene (first N)")
    p.add_argument("--size", default="160x120", help="WxH working size")
    p.add_argument("--variants", default="clean", help="comma-separated: clean, hard, outliers, flying")
    labels = p.add_mutually_exclusive_group()
    labels.add_argument("--noise", action="store_true", help="corrupted ground truth (default)")
    labels.add_argument("--labels", default=None, help="a label folder of the scene")
    labels.add_argument("--predictions", default=None, help="a segmentation network checkpoint")
    p.add_argument(
        "--space-labels",
        nargs="?",
        const="missing",
        default=None,
        choices=("missing", "all"),
        help="ground truth defined in 3D (csa_core.data.space_labels) for scenes without labels "
        "(missing, the default of the bare flag) or for every scene (all); with --noise only",
    )
    p.add_argument(
        "--presets",
        default="fast",
        help="comma-separated NeRF presets, or none; PRESET+KEY=VALUE+... adds that row's own "
        "overrides after --set (e.g. fast,fast+optim.semantic_steps=300)",
    )
    p.add_argument("--steps", type=int, default=None, help="override the presets' step counts")
    p.add_argument("--set", action="append", default=[], help="NeRF config override, a.b=value")
    p.add_argument(
        "--renders",
        default="",
        help=f"extra label renders of each NeRF fit, comma-separated: {', '.join(RENDERS)}, "
        "or config overrides joined by + (sampler.render_band_samples=12)",
    )
    p.add_argument("--voxel", type=float, default=0.05, help="voxel size of the map, metres")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="auto")
    p.add_argument(
        "--per-class", action="store_true", help="also print each fuser's IoU of every class"
    )
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    p.add_argument(
        "--capture", default="walk", choices=CAPTURES, help="capture mode of synth: scenes (walk)"
    )
    args = p.parse_args()
    if args.space_labels and (args.labels or args.predictions):
        raise SystemExit("--space-labels: only with --noise (not with --labels or --predictions)")
    bad = set(args.variants.split(",")) - {"clean", "hard", "outliers", "flying"}
    if bad:
        raise SystemExit(f"--variants: unknown {', '.join(sorted(bad))} (clean, hard, outliers, flying)")
    args.renders = [r for r in args.renders.split(",") if r]
    bad = {r for r in args.renders if r not in RENDERS and "=" not in r}
    if bad:
        raise SystemExit(
            f"--renders: unknown {', '.join(sorted(bad))} ({', '.join(RENDERS)}, or "
            "section.key=value overrides joined by +)"
        )
    from csa_core.device import resolve_device

    torch.set_num_threads(args.threads)
    for name in [n for n in args.presets.split(",") if n not in ("", "none")]:
        try:  # a bad preset or override fails before any work
            preset_config(name, args.set)
        except (CSAInputError, ValueError) as err:
            raise SystemExit(f"fusion_bench: {err}") from None
    try:
        args.size = parse_size(args.size)
        args.device_torch = resolve_device(None if args.device == "auto" else args.device)
        rows = run(args)
    except CSAInputError as err:
        raise SystemExit(f"fusion_bench: {err}") from None
    w, h = args.size
    how = rows[-1].get("peak_rss_how", "") if rows else ""
    print(
        f"\n{w}x{h}, up to {args.frames} frames per scene (first 80% train, last 20% val), "
        f"torch {torch.__version__}, {platform.machine()} {torch.get_num_threads()} threads, "
        f"device {args.device_torch}; peak RSS by {how}"
    )
    print(table(rows))
    if args.per_class:
        print(class_tables(rows))
    if any(r["fuser"].startswith("NeRF") and "class_iou_val" in r for r in rows):
        print("\nTargets (benchmarks/RESULTS.md \"Targets\"): IoU points against the map's better "
              "read-back; worst class among those of at least 1% of the pixels")
        print(targets_table(rows))
    if args.json:
        write_text_atomic(args.json, json.dumps({"argv": sys.argv, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
