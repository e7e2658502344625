"""How far the synthetic room families are apart for a segmentation network.

    python benchmarks/family_shift.py [--train-family apartment] [--train-scenes 8]
        [--frames 30] [--epochs 12] [--eval-scenes 3] [--size 160x120] [--threads 1] [--out CKPT]

Pre-trains the default light network from scratch on ``--train-scenes`` rooms of one family
(the training views of each room; the best epoch is picked on their validation views), then
scores it on all frames of ``--eval-scenes`` new rooms (seeds never used for training) of
every family. Prints a Markdown table: pretrain family, eval family, mIoU and pixel accuracy.
The first row is the training rooms' own validation views. Not a test: a run takes minutes.
"""

from __future__ import annotations

import argparse
import time

import torch

from csa_core.cli.args import size_arg
from csa_core.data.synth import family_names, generate_scene, scene_seed
from csa_core.eval.miou import ConfusionMatrix
from csa_core.seg.config import PretrainConfig, TrainConfig
from csa_core.seg.predict import evaluate_scene
from csa_core.seg.pretraining import pretrain

EVAL_OFFSET = 1000  # scene indices of evaluation rooms start here, far from the training ones


def _scenes(family: str, seed: int, indices: range, frames: int, size: tuple[int, int]) -> list:
    return [
        generate_scene(family, scene_seed(seed, k), frames, size, name=f"{family}_{k}")
        for k in indices
    ]


def _score(
    model: torch.nn.Module, scenes: list, split: str, size: tuple[int, int]
) -> tuple[float, float]:
    matrix = ConfusionMatrix()
    for scene in scenes:
        matrix.merge(evaluate_scene(model, scene, split=split, device="cpu", size=size))
    return 100.0 * matrix.miou(), 100.0 * matrix.pixel_accuracy()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--train-family", default="apartment", choices=family_names())
    p.add_argument("--eval-families", default=",".join(family_names()), help="comma-separated")
    p.add_argument("--train-scenes", type=int, default=8)
    p.add_argument("--eval-scenes", type=int, default=3)
    p.add_argument("--frames", type=int, default=30, help="frames per room")
    p.add_argument("--epochs", type=int, default=12)
    p.add_argument("--size", type=size_arg, default=(160, 120))
    p.add_argument("--seed", type=int, default=0, help="seed of the room batches and of training")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="also keep the checkpoint here (.safetensors)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    t0 = time.perf_counter()
    train = _scenes(args.train_family, args.seed, range(args.train_scenes), args.frames, args.size)
    evals = {
        fam: _scenes(
            fam,
            args.seed,
            range(EVAL_OFFSET, EVAL_OFFSET + args.eval_scenes),
            args.frames,
            args.size,
        )
        for fam in args.eval_families.split(",")
    }
    t_data = time.perf_counter() - t0

    config = PretrainConfig(
        size=args.size,
        train=TrainConfig(
            epochs=args.epochs, val_every=args.epochs, seed=args.seed, device="cpu", progress=False
        ),
    )
    t0 = time.perf_counter()
    model, _ = pretrain(train, config, out=args.out)
    t_train = time.perf_counter() - t0

    rows = [
        (
            args.train_family,
            f"{args.train_family} (training rooms, val views)",
            *_score(model, train, "val", args.size),
        )
    ]
    for fam, scenes in evals.items():
        rows.append(
            (args.train_family, f"{fam} (new rooms)", *_score(model, scenes, "all", args.size))
        )
    print(
        f"\n{args.train_scenes} x {args.frames} frames of {args.train_family} "
        f"at {args.size[0]}x{args.size[1]}, "
        f"{args.epochs} epochs; {args.eval_scenes} new rooms per family "
        f"(data {t_data:.0f} s, training {t_train:.0f} s)\n"
    )
    print("| pretrain family | eval family | mIoU % | pixel acc % |")
    print("|---|---|---|---|")
    for train_fam, eval_fam, miou, acc in rows:
        print(f"| {train_fam} | {eval_fam} | {miou:.1f} | {acc:.1f} |")


if __name__ == "__main__":
    main()
