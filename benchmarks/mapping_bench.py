"""Quality, size and speed of the two baselines on synthetic rooms; prints Markdown tables.

    python benchmarks/mapping_bench.py [--family office] [--frames 40] [--size 160x120]
                                       [--variants clean,hard] [--voxels 0.05,0.1]
                                       [--cotta-images 6] [--threads 1]
                                       [--backends torch,numpy] [--device cpu]
                                       [--clock wall]

Mapping: labels are fused in a voxel map (a TSDF plus class scores, ``build_voxel_map``) and
read back at every view, by ray casting to the TSDF's zero crossing (Mapping's read-back) and,
for comparison, through each view's own depth. Labels fused: the exact ground truth, and the
ground truth corrupted frame by frame (view-inconsistent errors, as a per-frame network makes);
``--variants hard`` first turns the room into a Kinect-like capture
(``csa_core.data.synth.kinect``: noisy depth with holes) and adds its labels with systematic
(view-consistent) and per-frame errors. The table gives mIoU over all pixels and agreement on
the pixels with (measured) depth against the ground truth, the share of pixels labelled, the
map's size (labelled voxels / TSDF voxels / bytes), the replay images Mapping must also keep,
the fusion seconds and the read-back seconds per view. CoTTA: seconds per online step of a
freshly built network (untrained: the number is speed only), for the paper's six scales and
the CPU subset, after one untimed step.

``--backends torch,numpy`` builds and reads every map with both implementations of the voxel
map (the torch one on ``--device``, and its numpy reference) and adds a table of their speed
ratios (numpy seconds / torch seconds: fusion, ray cast, depth read-back) and of how many
labels they share, in the same run on the same views. ``--clock cpu`` times the mapping with
the process's CPU seconds (all its threads) instead of wall seconds, which other work on a
shared machine moves less.
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
from csa_core.adapt.baselines.voxel_map import BACKENDS, VoxelMapConfig
from csa_core.data.label_noise import corrupt_labels
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.data.synth import NOISY_FOLDER, degrade_scene, generate_scene, parse_size
from csa_core.device import resolve_device
from csa_core.eval import ConfusionMatrix
from csa_core.seg.models import build_model

VARIANTS = ("clean", "hard")


def score(labels: dict[str, np.ndarray], scene: Scene) -> tuple[float, float, float]:
    """(mIoU over all pixels, agreement on pixels with depth, share of pixels labelled)
    against the ground truth."""
    matrix = ConfusionMatrix()
    hits = total = labelled = 0
    for frame in scene.frames:
        gt = frame.labels[NYU40_FOLDER]
        matrix.update(labels[frame.name], gt)
        m = frame.depth > 0
        hits += int((labels[frame.name][m] == gt[m]).sum())
        total += int(m.sum())
        labelled += int((labels[frame.name] > 0).sum())
    return matrix.miou(), hits / total, labelled / sum(f.depth.size for f in scene.frames)


def label_sets(scene: Scene, variant: str, seed: int) -> dict[str, dict[str, np.ndarray]]:
    """The per-frame labels to fuse, by what they are."""
    rng = np.random.default_rng(seed)
    sets = {
        "exact": {f.name: f.labels[NYU40_FOLDER] for f in scene.frames},
        "per-frame errors": {
            f.name: corrupt_labels(f.labels[NYU40_FOLDER], rng) for f in scene.frames
        },
    }
    if variant == "hard":
        sets["systematic + per-frame"] = {f.name: f.labels[NOISY_FOLDER] for f in scene.frames}
    return sets


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def mapping_rows(
    scene: Scene,
    variant: str,
    voxel_sizes: list[float],
    seed: int,
    backends: list[str],
    device: torch.device,
    ratios: list[str],
    clock=time.perf_counter,
) -> list[str]:
    """Rows of the quality table (seconds by ``clock``); with two backends, rows of the
    speed-ratio table go to ``ratios``."""
    rows = []
    for name, inputs in label_sets(scene, variant, seed).items():
        miou, agree, share = score(inputs, scene)
        rows.append(
            f"| {variant} | {name} | - | - | input | {100 * miou:.1f} | {100 * agree:.1f} "
            f"| {100 * share:.1f} | - | - | - | - |"
        )
        for size in voxel_sizes:
            seconds: dict[tuple[str, str], float] = {}
            labels: dict[tuple[str, str], dict[str, np.ndarray]] = {}
            for backend in backends:
                t0 = clock()
                voxel_map = build_voxel_map(
                    scene, inputs, VoxelMapConfig(voxel_size=size), device, backend
                )
                fuse = seconds[backend, "fuse"] = clock() - t0
                for read in READ_BACKS:
                    t0 = clock()
                    pseudo = render_map_labels(voxel_map, scene, list(inputs), read=read)
                    per_view = (clock() - t0) / len(inputs)
                    seconds[backend, read], labels[backend, read] = per_view, pseudo
                    miou, agree, share = score(pseudo, scene)
                    replay = mapping_memory(scene, pseudo).footprint()
                    rows.append(
                        f"| {variant} | {name} | {100 * size:.0f} cm | {backend} | {read} "
                        f"| {100 * miou:.1f} | {100 * agree:.1f} | {100 * share:.1f} "
                        f"| {voxel_map.num_voxels} / {voxel_map.num_tsdf_voxels} / "
                        f"{voxel_map.nbytes / 1e6:.2f} MB | {replay.replay_bytes / 1e6:.2f} MB "
                        f"| {fuse:.2f} | {per_view:.3f} |"
                    )
            if len(backends) == 2:
                a, b = backends
                same = [
                    np.mean([(labels[a, r][n] == labels[b, r][n]).mean() for n in inputs])
                    for r in READ_BACKS
                ]
                ratios.append(
                    f"| {variant} | {name} | {100 * size:.0f} cm | "
                    + " | ".join(
                        f"{seconds[b, k] / seconds[a, k]:.1f}" for k in ("fuse", *READ_BACKS)
                    )
                    + " | "
                    + " | ".join(f"{100 * v:.2f}" for v in same)
                    + " |"
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
    parser.add_argument(
        "--variants", default="clean", help="comma-separated: clean, hard (Kinect-like capture)"
    )
    parser.add_argument("--voxels", default="0.05,0.1", help="voxel sizes in metres")
    parser.add_argument("--arch", default="lraspp_mobilenet_v3_large")
    parser.add_argument("--cotta-images", type=int, default=6, help="0 skips CoTTA")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--backends", default="torch", help="voxel map implementations: torch, numpy or both"
    )
    parser.add_argument("--device", default="cpu", help="the torch voxel map's device")
    parser.add_argument(
        "--clock", default="wall", choices=sorted(CLOCKS), help="the mapping's seconds"
    )
    args = parser.parse_args()
    variants = args.variants.split(",")
    bad = set(variants) - set(VARIANTS)
    if bad:
        parser.error(f"--variants: unknown {', '.join(sorted(bad))} (choose from clean, hard)")
    backends = args.backends.split(",")
    if not backends or set(backends) - set(BACKENDS) or len(set(backends)) != len(backends):
        parser.error(f"--backends: {args.backends!r}, expected one or both of {BACKENDS}")
    device = resolve_device(args.device)
    torch.set_num_threads(args.threads)
    scene = generate_scene(args.family, args.seed, args.frames, parse_size(args.size))
    w, h = scene.size
    print(
        f"Mapping on {scene.name}: {len(scene)} frames at {w}x{h}, {args.threads} thread(s), "
        f"torch map on {device}, {args.clock} seconds\n"
    )
    print(
        "| capture | labels | voxel | map | read-back | mIoU % | agreement % | labelled % "
        "| voxels (labelled / TSDF) / map | replay images | fuse s | read s / view |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    sizes = [float(v) for v in args.voxels.split(",")]
    ratios: list[str] = []
    for variant in variants:
        captured = degrade_scene(scene, args.seed) if variant == "hard" else scene
        rows = mapping_rows(
            captured, variant, sizes, args.seed, backends, device, ratios, CLOCKS[args.clock]
        )
        for row in rows:
            print(row, flush=True)
    if ratios:
        a, b = backends
        print(f"\nSpeed of the {a} map over the {b} map (their seconds' ratio), same views\n")
        print(
            "| capture | labels | voxel | fuse | ray cast | depth read-back "
            "| equal ray-cast labels % | equal depth labels % |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for row in ratios:
            print(row)
    if args.cotta_images > 0:
        print(f"\nCoTTA online steps at {w}x{h}, {args.threads} thread(s)\n")
        print("| network | scales | teacher passes | s / image | extra copies | Adam state |")
        print("|---|---|---|---|---|---|")
        for row in cotta_rows(scene, args.arch, args.cotta_images):
            print(row)


if __name__ == "__main__":
    main()
