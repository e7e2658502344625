"""Throughput of the segmentation networks on this machine: training images/s, inference ms/image.

    python benchmarks/seg_bench.py [--archs lraspp_mobilenet_v3_large,...|all] [--threads N]

Random inputs and labels, Adam steps at batch 8 (training) and batched no-grad forward
passes (inference), after warm-up steps that are not timed. Prints a Markdown table. Always
on CPU; ``all`` adds the ResNet DeepLabs, which take minutes per row there.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import torch

from csa_core.seg.config import ARCH_NAMES
from csa_core.seg.losses import segmentation_loss
from csa_core.seg.models import build_model, count_parameters

LIGHT = ("lraspp_mobilenet_v3_large", "deeplabv3_mobilenet_v3_large")
SIZES = ((160, 120), (320, 240))


def _timed(fn, warmup: int, repeats: int) -> float:
    """Median seconds of ``fn`` over ``repeats`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def bench(arch: str, size: tuple[int, int], batch: int, repeats: int) -> tuple[float, float]:
    """(training images/s, inference ms/image) of ``arch`` at ``size`` (width, height)."""
    torch.manual_seed(0)
    model = build_model(arch)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    w, h = size
    x = torch.rand(batch, 3, h, w)
    y = torch.randint(0, 41, (batch, h, w))

    def train_step() -> None:
        model.train()
        loss = segmentation_loss(model(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def infer() -> None:
        model.eval()
        with torch.no_grad():
            model(x)

    train_s = _timed(train_step, warmup=1, repeats=repeats)
    infer_s = _timed(infer, warmup=1, repeats=repeats)
    return batch / train_s, 1000.0 * infer_s / batch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--archs", default=",".join(LIGHT), help="comma-separated architectures, or 'all'"
    )
    parser.add_argument(
        "--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)"
    )
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument(
        "--repeats", type=int, default=3, help="timed repetitions (median reported)"
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    archs = ARCH_NAMES if args.archs == "all" else tuple(a for a in args.archs.split(",") if a)
    print(
        f"torch {torch.__version__} on CPU ({platform.machine()}), {torch.get_num_threads()} "
        f"of {os.cpu_count()} cores, batch {args.batch}"
    )
    print()
    print("| arch | params (M) | size | train (images/s) | inference (ms/image) |")
    print("|---|---:|---|---:|---:|")
    for arch in archs:
        params = count_parameters(build_model(arch)) / 1e6
        for size in SIZES:
            train_ips, infer_ms = bench(arch, size, args.batch, args.repeats)
            print(
                f"| {arch} | {params:.1f} | {size[0]}x{size[1]} "
                f"| {train_ips:.1f} | {infer_ms:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
