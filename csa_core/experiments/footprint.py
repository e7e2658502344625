"""Experiment ``footprint``: what each method must keep to remember the scenes it has seen.

After 1..T scenes, in bytes: ours keeps one NeRF checkpoint per scene (fp16, the memory
bank's storage; fp32 for reference); Mapping keeps its voxel map plus the training images and
map labels it must replay (raw arrays, and as PNG files); CoTTA keeps two extra copies of the
network (teacher and source) whatever the number of scenes. Rows that all replaying methods
share are listed too: the replay buffer (``buffer_size`` pairs held in memory while adapting;
ours renders it, Mapping's is a view of its stored pairs) and the pre-training slice.

Sizes are measured on the artefacts themselves, without adapting the network: a NeRF
checkpoint holds dense tensors of fixed shapes, so its size depends on the config and the
number of training views, not on training (the NeRF is built by a zero-step fit); the voxel
map's size depends on the depth maps only. So the experiment costs seconds, not NeRF fits,
and the seeds give no spread (the columns' std is 0 by construction).
"""

from __future__ import annotations

import numpy as np

from csa_core.adapt.baselines.cotta import CoTTA
from csa_core.adapt.baselines.mapping import build_voxel_map, mapping_memory, render_map_labels
from csa_core.adapt.config import nerf_config
from csa_core.adapt.methods import cotta_config, pretrain_context
from csa_core.adapt.pseudo_labels import PREDICTION_FOLDER, predict_frames, with_labels
from csa_core.data.scene import Scene
from csa_core.experiments.inputs import ExperimentInputs
from csa_core.experiments.report import (
    ExperimentReport,
    Plot,
    Series,
    byte_unit,
    markdown_table,
    mean_std,
)
from csa_core.nerf.checkpoint import checkpoint_bytes
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.seg.models import SegmentationNet

NAME = "footprint"
# (key, method, title) of the table's rows.
ROWS: tuple[tuple[str, str, str], ...] = (
    ("nerf_fp16", "ours", "CSA: NeRF checkpoints (fp16)"),
    ("nerf_fp32", "ours", "CSA: NeRF checkpoints (fp32)"),
    ("mapping_raw", "mapping", "Mapping: map + images (raw arrays)"),
    ("mapping_png", "mapping", "Mapping: map + images (PNG files)"),
    ("cotta", "cotta", "CoTTA: teacher + source copies"),
    ("replay_buffer", "ours, mapping", "replay buffer while adapting (RAM)"),
    ("pretrain_replay", "ours, mapping", "pre-training slice (RAM)"),
)


def scene_bytes(
    model: SegmentationNet, scene: Scene, inputs: ExperimentInputs, seed: int
) -> dict[str, int]:
    """Bytes each method stores for one scene (see the module docstring)."""
    config = inputs.config(seed)
    frames = scene.train_frames
    predictions = predict_frames(model, frames, device=config.seg.device)
    labelled = with_labels(scene, PREDICTION_FOLDER, predictions)
    nerf, _ = fit_semantic_nerf(
        labelled,
        PREDICTION_FOLDER,
        nerf_config(config.nerf),
        device=config.seg.device,
        steps=0,
        progress=False,
    )
    voxel_map = build_voxel_map(scene, predictions)
    memory = mapping_memory(
        scene, render_map_labels(voxel_map, scene, list(predictions)), voxel_map
    )
    return {
        "nerf_fp16": len(checkpoint_bytes(nerf, "float16")),
        "nerf_fp32": len(checkpoint_bytes(nerf, "float32")),
        "mapping_raw": memory.footprint().total_bytes,
        "mapping_png": memory.footprint(".png").total_bytes,
    }


def run(inputs: ExperimentInputs) -> ExperimentReport:
    """Cumulative bytes per method after each scene, for every seed."""
    T = len(inputs.scenes)
    totals: dict[str, list[list[float]]] = {key: [] for key, _, _ in ROWS}  # seeds x T
    runs = []
    model = inputs.network()
    w, h = inputs.scenes[0].size
    for seed in inputs.seeds:
        config = inputs.config(seed)
        per_scene = [scene_bytes(model, s, inputs, seed) for s in inputs.scenes]
        for key in ("nerf_fp16", "nerf_fp32", "mapping_raw", "mapping_png"):
            totals[key].append(np.cumsum([b[key] for b in per_scene]).tolist())
        copies = CoTTA(inputs.network(), cotta_config(config)).footprint().extra_copies_bytes
        totals["cotta"].append([copies] * T)
        pair = w * h * 3 + w * h  # uint8 RGB image + uint8 label map
        totals["replay_buffer"].append([config.replay.buffer_size * pair] * T)
        pretrain, _ = pretrain_context(inputs.pretrain_scenes, config)
        totals["pretrain_replay"].append([pretrain.nbytes() if pretrain is not None else 0] * T)
        runs.append(
            {
                "seed": seed,
                "per_scene": {s.name: b for s, b in zip(inputs.scenes, per_scene, strict=True)},
                "cotta_copies": copies,
                "config": config.to_dict(),
            }
        )
    if not inputs.pretrain_scenes:
        del totals["pretrain_replay"]
    return _report(inputs, totals, runs)


def _report(
    inputs: ExperimentInputs, totals: dict[str, list[list[float]]], runs: list[dict]
) -> ExperimentReport:
    n = len(inputs.seeds)
    T = len(inputs.scenes)
    rows_meta = [r for r in ROWS if r[0] in totals]
    stats = {
        key: [mean_std(seed_row[i] for seed_row in totals[key]) for i in range(T)]
        for key, _, _ in rows_meta
    }
    unit, scale = byte_unit(m for key in stats for m, _ in stats[key])
    positive = [m for key in stats for m, _ in stats[key] if m > 0]
    header = ["stored", "method", *(f"{k} scene{'s' * (k > 1)}" for k in range(1, T + 1))]
    rows, csv_rows, series = [], [], []
    for key, method, title in rows_meta:
        rows.append([title, method, *(f"{m / scale:.2f}" for m, _ in stats[key])])
        for i, (m, s) in enumerate(stats[key]):
            csv_rows.append([key, method, i + 1, m, s, n])
        series.append(
            Series(
                title,
                list(range(1, T + 1)),
                [m / scale for m, _ in stats[key]],
                style="-" if key.startswith(("nerf", "mapping", "cotta")) else ":",
            )
        )
    md = (
        f"### Memory footprint in {unit} after 1..{T} scenes (preset {inputs.preset}, "
        f"{inputs.scenes[0].size[0]}x{inputs.scenes[0].size[1]})\n\n" + markdown_table(header, rows)
    )
    plot = Plot(
        file=f"{NAME}.png",
        title="Memory kept per method",
        xlabel="scenes seen",
        ylabel=unit,
        series=series,
        xticks=list(range(1, T + 1)),
        logy=bool(positive) and max(positive) > 20 * min(positive),
    )
    return ExperimentReport(
        name=NAME,
        markdown=md,
        csv_header=["stored", "method", "scenes", "bytes_mean", "bytes_std", "seeds"],
        csv_rows=csv_rows,
        runs=runs,
        plots=[plot],
    )
