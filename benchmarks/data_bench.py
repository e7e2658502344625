"""Data-layer timings: synthetic room generation per family and scene reading.

Prints a table; not a test. Usage:
    python benchmarks/data_bench.py [--frames 60] [--size 160x120] [--seven-scenes PATH]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from csa_core.cli.args import size_arg
from csa_core.data.scene_io import read_scene, write_scene
from csa_core.data.sevenscenes import load_7scenes
from csa_core.data.synth import FAMILIES, generate_scene


def timed(fn, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", type=size_arg, default=(160, 120))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seven-scenes", type=Path, default=Path("../shared/data/7scenes-kitchen-100"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    w, h = args.size
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for fam in FAMILIES:
            dest = Path(tmp) / fam
            sec, scene = timed(
                lambda fam=fam: generate_scene(fam, 0, args.frames, args.size), args.repeats
            )
            wsec, _ = timed(
                lambda scene=scene, dest=dest: write_scene(scene, dest, overwrite=True), 1
            )
            rsec, _ = timed(lambda dest=dest: read_scene(dest), args.repeats)
            rows.append((f"synth {fam}", f"{args.frames} x {w}x{h}", sec, wsec, rsec))
        if args.seven_scenes.is_dir():
            sec, scene = timed(
                lambda: load_7scenes(args.seven_scenes, size=args.size), args.repeats
            )
            wsec, _ = timed(
                lambda: write_scene(scene, Path(tmp) / "7s", overwrite=True, color_ext=".jpg"), 1
            )
            rsec, _ = timed(lambda: read_scene(Path(tmp) / "7s"), args.repeats)
            rows.append(("7-Scenes import", f"{len(scene)} x 640x480 -> {w}x{h}", sec, wsec, rsec))
    print(f"{'what':24s} {'frames':26s} {'make s':>8s} {'write s':>8s} {'read s':>8s}")
    for name, frames, make, write, read in rows:
        print(f"{name:24s} {frames:26s} {make:8.2f} {write:8.2f} {read:8.2f}")


if __name__ == "__main__":
    main()
