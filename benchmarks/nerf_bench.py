"""Semantic-NeRF benchmark: fit time, throughput, render time, held-out PSNR and depth error,
label mIoU and checkpoint size, per preset. Prints a markdown table (not a test).

Examples (run from the repository root):

    python benchmarks/nerf_bench.py --scene 7scenes:../shared/data/7scenes-kitchen-100 --size 160x120
    python benchmarks/nerf_bench.py --scene synth:apartment:3 --frames 60 --size 80x60 --noise
    python benchmarks/nerf_bench.py --scene synth:apartment:3 --presets fast,reference --steps 400

Held-out = the scene's validation frames (last 20%). On synthetic scenes with ``--noise`` the
labels fused are corrupted per frame (``csa_core.nerf.label_noise``) and the table reports mIoU
vs ground truth of the corrupted inputs and of the labels rendered at the training views.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from csa_core.eval.miou import ConfusionMatrix
from csa_core.nerf.checkpoint import checkpoint_bytes
from csa_core.nerf.config import preset
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.label_noise import corrupt_labels
from csa_core.nerf.render import render_image


def load_scene(spec: str, size: tuple[int, int], frames: int):
    kind, _, rest = spec.partition(":")
    if kind == "7scenes":
        from csa_core.data.sevenscenes import load_7scenes

        return load_7scenes(rest, size=size), False
    if kind == "synth":
        from csa_core.data.synth import generate_scene

        family, _, seed = rest.partition(":")
        return generate_scene(family or "apartment", int(seed or 0), frames, size), True
    if kind == "folder":
        from csa_core.data.scene_io import read_scene

        return read_scene(rest, size=size, labels="all"), True
    raise SystemExit(f"unknown --scene {spec!r} (7scenes:PATH, synth:FAMILY:SEED or folder:PATH)")


def psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * np.log10(mse)


def run(args: argparse.Namespace) -> list[dict]:
    scene, has_gt = load_scene(args.scene, args.size, args.frames)
    labels = None
    if has_gt:
        labels = "label-nyu40"
        if args.noise:
            rng = np.random.default_rng(args.seed)
            for f in scene.frames:
                f.labels["noisy"] = corrupt_labels(f.labels["label-nyu40"], rng)
            labels = "noisy"
    rows = []
    for name in args.presets.split(","):
        cfg = preset(name)
        if args.rays:
            cfg.optim.rays_per_step = args.rays
        if args.log2_table:
            cfg.field.encoding.log2_table_size = args.log2_table
        nerf, stats = fit_semantic_nerf(
            scene, labels, cfg, device=args.device, steps=args.steps, progress=not args.quiet
        )
        row = {
            "preset": name,
            "steps": stats.steps,
            "fit_s": stats.seconds,
            "rays_s": stats.rays_per_second,
            "samples_s": stats.samples_per_second,
            "occupied": stats.occupied_fraction,
        }
        # Held-out colour and depth.
        val = scene.val_frames[:: args.val_every]
        mses, derr, times = [], [], []
        for f in val:
            t0 = time.perf_counter()
            v = render_image(nerf, f.pose, scene.intrinsics, semantics=labels is not None)
            times.append(time.perf_counter() - t0)
            mses.append(float(np.mean((v.color.astype(np.float64) - f.color) ** 2) / 255.0**2))
            if f.depth is not None and (f.depth > 0).any():
                m = f.depth > 0
                derr.append(float(np.mean(np.abs(v.depth[m] - f.depth[m]))))
        row["val_psnr"] = psnr(float(np.mean(mses)))
        row["val_depth_l1_m"] = float(np.mean(derr)) if derr else float("nan")
        row["render_s_per_img"] = float(np.mean(times))
        # Labels at the training views.
        if labels is not None:
            cm_in, cm_out, cm_vs_in = ConfusionMatrix(), ConfusionMatrix(), ConfusionMatrix()
            for f in scene.train_frames[:: args.label_every]:
                v = render_image(nerf, f.pose, scene.intrinsics)
                gt = f.labels["label-nyu40"]
                cm_in.update(f.labels[labels], gt)
                cm_out.update(v.labels, gt)
                cm_vs_in.update(v.labels, f.labels[labels])
            row["miou_input"] = cm_in.miou()
            row["miou_rendered"] = cm_out.miou()
            row["miou_rendered_vs_input"] = cm_vs_in.miou()
        row["ckpt_fp16_mb"] = len(checkpoint_bytes(nerf, "float16")) / 1e6
        row["ckpt_fp32_mb"] = len(checkpoint_bytes(nerf, "float32")) / 1e6
        if args.save:
            out = Path(args.save) / f"{scene.name}-{name}.safetensors"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(checkpoint_bytes(nerf))
        rows.append(row)
    return rows


COLUMNS = [
    ("preset", "{}"),
    ("steps", "{}"),
    ("fit_s", "{:.0f}"),
    ("rays_s", "{:,.0f}"),
    ("samples_s", "{:,.0f}"),
    ("render_s_per_img", "{:.2f}"),
    ("val_psnr", "{:.2f}"),
    ("val_depth_l1_m", "{:.3f}"),
    ("miou_input", "{:.3f}"),
    ("miou_rendered", "{:.3f}"),
    ("miou_rendered_vs_input", "{:.3f}"),
    ("ckpt_fp16_mb", "{:.2f}"),
    ("ckpt_fp32_mb", "{:.2f}"),
]


def table(rows: list[dict]) -> str:
    cols = [c for c, _ in COLUMNS if any(c in r for r in rows)]
    fmt = dict(COLUMNS)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(fmt[c].format(r[c]) if c in r else "-" for c in cols) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scene", required=True, help="7scenes:PATH, synth:FAMILY:SEED or folder:PATH")
    p.add_argument("--size", default="160x120", help="WxH working size")
    p.add_argument("--frames", type=int, default=100, help="frames of a synthetic scene")
    p.add_argument("--presets", default="fast", help="comma-separated presets")
    p.add_argument("--steps", type=int, default=None, help="override the presets' step counts")
    p.add_argument("--rays", type=int, default=None, help="override rays per step")
    p.add_argument("--log2-table", type=int, default=None, help="override the hash table size")
    p.add_argument(
        "--noise", action="store_true", help="fuse per-frame corrupted labels (synthetic scenes)"
    )
    p.add_argument("--val-every", type=int, default=1, help="evaluate every N-th held-out frame")
    p.add_argument(
        "--label-every", type=int, default=1, help="evaluate labels on every N-th training frame"
    )
    p.add_argument("--device", default="auto")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", default=None, help="folder to keep the checkpoints in")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args()
    args.size = tuple(int(v) for v in args.size.lower().split("x"))
    torch.set_num_threads(args.threads)
    rows = run(args)
    print(
        f"\nscene {args.scene} at {args.size[0]}x{args.size[1]}, torch {torch.__version__}, "
        f"{platform.machine()} {torch.get_num_threads()} threads, device {args.device}"
    )
    print(table(rows))


if __name__ == "__main__":
    main()
