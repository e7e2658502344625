"""How far any label fuser can get on the hard variant of the fusion benchmark (not a test).

The hard variant (``csa_core/data/synth/kinect.py``) gives each frame two kinds of label
error: per-frame ones, which differ from view to view, and systematic ones, which are the same
in every view that sees a region. Fusing views can remove the first kind only. So the
systematic errors alone, without any per-frame noise, are what a perfect consensus of the views
gives: their mIoU is the ceiling of every fuser that keeps what the views agree on (the map,
the NeRF). The table also fuses the hard labels with the clean depth instead of the Kinect-like
one, to show what the depth noise and holes cost the map.

    python benchmarks/hard_ceiling.py --families all --frames 250 --size 160x120

Rows per family: the labels themselves and the map (Mapping's 5 cm fusion, read back by ray
casting, as in ``fusion_bench.py``), mIoU on the training views / the held-out views (the
scene's last 20%; the map fuses the training views only).
"""

from __future__ import annotations

import argparse
import dataclasses

import torch
from fusion_bench import miou, open_scene

from csa_core.adapt.baselines.mapping import build_voxel_map, render_map_labels
from csa_core.adapt.baselines.voxel_map import VoxelMapConfig
from csa_core.data.scene import Scene
from csa_core.data.synth import degrade_scene, family_names, parse_size
from csa_core.data.synth.kinect import KinectConfig


def scores(scene: Scene, folder: str, voxel: float) -> tuple[float, float, float, float]:
    """mIoU of the labels in ``folder`` and of the map fused from them: train, val, train, val."""
    labels = {f.name: f.labels[folder] for f in scene.frames}
    train, val = scene.train_frames, scene.val_frames
    fused = build_voxel_map(
        scene, {f.name: labels[f.name] for f in train}, VoxelMapConfig(voxel_size=voxel)
    )
    cast = render_map_labels(fused, scene, [f.name for f in scene.frames])
    return miou(labels, train), miou(labels, val), miou(cast, train), miou(cast, val)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--families", default="all", help="'all' or comma-separated families")
    p.add_argument("--seed", type=int, default=0, help="room seed and noise seed")
    p.add_argument("--frames", type=int, default=250)
    p.add_argument("--size", default="160x120", help="WxH working size")
    p.add_argument("--voxel", type=float, default=0.05, help="voxel size of the map, metres")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    size = parse_size(args.size)
    names = family_names() if args.families == "all" else args.families.split(",")
    print("| family | labels | depth | labels: train / val | map: train / val |")
    print("|---|---|---|---|---|")
    for name in names:
        scene, _ = open_scene(f"synth:{name}:{args.seed}", size, args.frames)
        systematic = degrade_scene(scene, args.seed, KinectConfig(frame_noise=None), target="sys")
        hard = degrade_scene(scene, args.seed, target="hard")
        rows = [("systematic only (the ceiling)", "Kinect-like", systematic, "sys")]
        rows.append(("systematic + per-frame (the hard variant)", "Kinect-like", hard, "hard"))
        clean_depth = Scene(
            name=hard.name,
            intrinsics=hard.intrinsics,
            frames=[
                dataclasses.replace(f, depth=c.depth)
                for f, c in zip(hard.frames, scene.frames, strict=True)
            ],
        )
        rows.append(("systematic + per-frame", "clean", clean_depth, "hard"))
        for what, depth, s, folder in rows:
            lt, lv, mt, mv = (100 * x for x in scores(s, folder, args.voxel))
            print(f"| {name} | {what} | {depth} | {lt:.1f} / {lv:.1f} | {mt:.1f} / {mv:.1f} |")
    print(f"\n{args.frames} frames at {size[0]}x{size[1]}, seed {args.seed}, map {args.voxel} m")


if __name__ == "__main__":
    main()
