"""Quality, size and speed of the two baselines on synthetic rooms; prints Markdown tables.

    python benchmarks/mapping_bench.py [--family office] [--frames 40] [--size 160x120]
                                       [--voxels 0.05,0.1] [--cotta-images 6] [--threads 1]

Mapping: the scene's ground-truth labels are corrupted frame by frame (view-inconsistent
errors, as a per-frame network makes), fused in a voxel map and read back at every view,
by ray casting (Mapping's read-back) and, for comparison, through each view's own depth;
the table compares mIoU and pixel agreement (pixels with depth) of the noisy inputs and the
map's pseudo-labels, with the map's size, the replay images Mapping must also keep, and the
fusion time. CoTTA: seconds per online step of a freshly built network (untrained: the
number is speed only), for the paper's six scales and the CPU subset, after one untimed step.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from csa_core.adapt.baselines.cotta import CoTTA, CoTTAConfig
from csa_core.adapt.baselines.mapping import (
    READ_BACKS,
    build_voxel_map,
    mapping_memory,
    render_map_labels,
)
from csa_core.adapt.baselines.voxel_map import VoxelMapConfig
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.data.synth import generate_scene, parse_size
from csa_core.eval import ConfusionMatrix
from csa_core.nerf.label_noise import corrupt_labels
from csa_core.seg.models import build_model


def score(labels: dict[str, np.ndarray], scene: Scene) -> tuple[float, float]:
    """(mIoU over all pixels, agreement on pixels with depth) against the ground truth."""
    matrix = ConfusionMatrix()
    hits = total = 0
    for frame in scene.frames:
        gt = frame.labels[NYU40_FOLDER]
        matrix.update(labels[frame.name], gt)
        m = frame.depth > 0
        hits += int((labels[frame.name][m] == gt[m]).sum())
        total += int(m.sum())
    return matrix.miou(), hits / total


def mapping_rows(scene: Scene, voxel_sizes: list[float], seed: int) -> list[str]:
    rng = np.random.default_rng(seed)
    noisy = {f.name: corrupt_labels(f.labels[NYU40_FOLDER], rng) for f in scene.frames}
    miou, agree = score(noisy, scene)
    rows = [f"| per-frame (corrupted) | - | - | {100 * miou:.1f} | {100 * agree:.1f} | - | - | - |"]
    for size in voxel_sizes:
        t0 = time.perf_counter()
        voxel_map = build_voxel_map(scene, noisy, VoxelMapConfig(voxel_size=size))
        t1 = time.perf_counter()
        for read in READ_BACKS:
            t2 = time.perf_counter()
            pseudo = render_map_labels(voxel_map, scene, list(noisy), read=read)
            t3 = time.perf_counter()
            miou, agree = score(pseudo, scene)
            replay = mapping_memory(scene, pseudo).footprint()
            rows.append(
                f"| Mapping | {100 * size:.0f} cm | {read} | {100 * miou:.1f} | {100 * agree:.1f} "
                f"| {voxel_map.num_voxels} / {voxel_map.nbytes / 1e6:.2f} MB "
                f"| {replay.replay_bytes / 1e6:.2f} MB | {t1 - t0:.2f} + {t3 - t2:.2f} |"
            )
    return rows


def cotta_rows(scene: Scene, arch: str, images: int) -> list[str]:
    rows = []
    for name, config in (("paper", CoTTAConfig()), ("cpu", CoTTAConfig.cpu())):
        torch.manual_seed(0)
        cotta = CoTTA(build_model(arch), config)
        frames = scene.frames[: images + 1]
        cotta.step(frames[0].color)
        t0 = time.perf_counter()
        cotta.adapt(frames[1:])
        per_image = (time.perf_counter() - t0) / max(1, len(frames) - 1)
        passes = len(config.scales) * (2 if config.flip else 1)
        fp = cotta.footprint()
        rows.append(
            f"| {arch} | {name} | {passes} | {per_image:.2f} "
            f"| {fp.extra_copies_bytes / 1e6:.1f} MB | {fp.optimizer_bytes / 1e6:.1f} MB |"
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="office")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--voxels", default="0.05,0.1", help="voxel sizes in metres")
    parser.add_argument("--arch", default="lraspp_mobilenet_v3_large")
    parser.add_argument("--cotta-images", type=int, default=6, help="0 skips CoTTA")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene = generate_scene(args.family, args.seed, args.frames, parse_size(args.size))
    w, h = scene.size
    print(f"Mapping on {scene.name}: {len(scene)} frames at {w}x{h}, corrupted ground truth\n")
    print(
        "| labels | voxel | read-back | mIoU % | agreement % | voxels / map | replay images "
        "| fuse + read s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for row in mapping_rows(scene, [float(v) for v in args.voxels.split(",")], args.seed):
        print(row)
    if args.cotta_images > 0:
        print(f"\nCoTTA online steps at {w}x{h}, {args.threads} thread(s)\n")
        print("| network | scales | teacher passes | s / image | extra copies | Adam state |")
        print("|---|---|---|---|---|---|")
        for row in cotta_rows(scene, args.arch, args.cotta_images):
            print(row)


if __name__ == "__main__":
    main()
