"""Semantic-NeRF benchmark: fit time, throughput, render time, held-out PSNR and depth error,
label mIoU and checkpoint size, per preset. Prints a markdown table (not a test).

Examples (run from the repository root):

    python benchmarks/nerf_bench.py --scene 7scenes:../shared/data/7scenes-kitchen-100 \
        --size 160x120
    python benchmarks/nerf_bench.py --scene synth:apartment:3 --frames 60 --size 80x60 --noise
    python benchmarks/nerf_bench.py --scene synth:apartment:3 --presets fast,reference --steps 400

    python benchmarks/nerf_bench.py --scene 7scenes:../shared/data/7scenes-kitchen-100 \
        --size 160x120 --color-camera kinect --appearance affine --holdout every:5

Held-out (``--holdout``): ``tail`` = the scene's validation frames (last 20% of the trajectory,
the project's protocol); ``every:N`` = every N-th frame (interleaved, the usual NeRF protocol),
training on the others. ``--color-camera kinect`` moves 7-Scenes frames to the Kinect colour
camera (``csa_core.data.registration``). On synthetic scenes with ``--noise`` the labels fused
are corrupted per frame (``csa_core.data.label_noise``). The table then reports mIoU vs ground
truth of the corrupted inputs and of the labels rendered at the training and held-out views
(each with its measured depth, as pseudo-labels are made; ``miou_val_novel``: held-out views
rendered without depth). For the voxel-map fusion of the same labels beside each preset, and
for the Kinect-like hard variant of a scene, use ``benchmarks/fusion_bench.py``.
``labels_s_per_view``: labels of a view with depth; ``--time-pairs`` adds ``pairs_s_per_view``,
colour and labels of the same views (what training on rendered images needs), and whether their
labels equal the labels-only ones; ``novel_s_per_view``: colour and labels of a
view without depth; ``total_s``: fit plus the labels of every frame of the scene.
``--reload`` renders everything from the checkpoint written in the storage dtype and read back.

    python benchmarks/nerf_bench.py --scene synth:office:0 --frames 250 --noise --presets fast
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from csa_core.data.label_noise import corrupt_labels
from csa_core.data.registration import (
    KINECT_V1_COLOR,
    color_consistency_rms,
    estimate_color_camera,
    to_color_camera,
)
from csa_core.errors import CSAInputError
from csa_core.eval.miou import ConfusionMatrix
from csa_core.nerf.appearance import nearest_frame
from csa_core.nerf.checkpoint import checkpoint_bytes, load_checkpoint, save_checkpoint
from csa_core.nerf.config import preset
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.render import render_frames, render_image
from csa_core.overrides import apply_overrides


def load_scene(spec: str, size: tuple[int, int], frames: int):
    kind, _, rest = spec.partition(":")
    if kind == "7scenes":
        from csa_core.data.sevenscenes import load_7scenes

        return load_7scenes(rest, size=size, camera="depth"), False  # --color-camera moves it
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


def image_mse(rendered: np.ndarray, image: np.ndarray) -> float:
    """Mean squared error of a rendered uint8 colour image against the camera's, in [0, 1] units."""
    return float(np.mean((rendered.astype(np.float64) - image) ** 2) / 255.0**2)


def split_frames(scene, holdout: str):
    """(training, held-out) frames: ``tail`` = the scene's split, ``every:N`` = every N-th frame
    (starting at N // 2) held out."""
    if holdout == "tail":
        return scene.train_frames, scene.val_frames
    kind, _, n = holdout.partition(":")
    if kind != "every" or not n.isdigit() or int(n) < 2:
        raise SystemExit(f"unknown --holdout {holdout!r} (tail or every:N, N >= 2)")
    n = int(n)
    held = set(range(n // 2, len(scene.frames), n))
    return (
        [f for i, f in enumerate(scene.frames) if i not in held],
        [f for i, f in enumerate(scene.frames) if i in held],
    )


def color_camera(scene, spec: str):
    """The scene at its colour camera (``kinect``: the measured Kinect v1 camera, ``estimate``:
    searched from it on this scene) and a description, or the scene unchanged for ``none``."""
    if spec == "none":
        return scene, "depth camera"
    cam = KINECT_V1_COLOR
    if spec == "estimate":
        cam, _ = estimate_color_camera(scene, KINECT_V1_COLOR)
    elif spec != "kinect":
        raise SystemExit(f"unknown --color-camera {spec!r} (none, kinect, estimate)")
    before, after = color_consistency_rms(scene, None), color_consistency_rms(scene, cam)
    k = cam.intrinsics
    desc = (
        f"colour camera f={k.fx:.1f} c=({k.cx:.1f}, {k.cy:.1f}) at {k.width}x{k.height}, "
        f"offset {cam.offset} m; multi-view colour RMS {before:.1f} -> {after:.1f}"
    )
    return to_color_camera(scene, cam), desc


def label_miou(labels: dict, frames) -> float:
    matrix = ConfusionMatrix()
    for f in frames:
        matrix.update(labels[f.name], f.labels["label-nyu40"])
    return matrix.miou()


def run(args: argparse.Namespace) -> list[dict]:
    scene, has_gt = load_scene(args.scene, args.size, args.frames)
    scene, cam_desc = color_camera(scene, args.color_camera)
    print(f"camera: {cam_desc}")
    labels = None
    if has_gt:
        labels = "label-nyu40"
        if args.noise:
            rng = np.random.default_rng(args.seed)
            for f in scene.frames:
                f.labels["noisy"] = corrupt_labels(f.labels["label-nyu40"], rng)
            labels = "noisy"
    train, held_out = split_frames(scene, args.holdout)
    rows = []
    for name in args.presets.split(","):
        cfg = preset(name)
        if args.rays:
            cfg.optim.rays_per_step = args.rays
        if args.log2_table:
            cfg.field.encoding.log2_table_size = args.log2_table
        if args.appearance:
            cfg.appearance = args.appearance
        if args.storage_dtype:
            cfg.storage_dtype = args.storage_dtype
        try:
            apply_overrides(cfg, args.set)
        except CSAInputError as err:
            raise SystemExit(f"nerf_bench: {err}") from None
        nerf, stats = fit_semantic_nerf(
            scene,
            labels,
            cfg,
            device=args.device,
            frames=train,
            steps=args.steps,
            progress=not args.quiet,
        )
        row = {
            "preset": name,
            "steps": stats.steps,
            "fit_s": stats.seconds,
            "rays_s": stats.rays_per_second,
            "samples_s": stats.samples_per_second,
            "occupied": stats.occupied_fraction,
        }
        row["ckpt_fp16_mb"] = len(checkpoint_bytes(nerf, "float16")) / 1e6
        row["ckpt_fp32_mb"] = len(checkpoint_bytes(nerf, "float32")) / 1e6
        if args.save:
            out = Path(args.save) / f"{scene.name}-{name}.safetensors"
            out.parent.mkdir(parents=True, exist_ok=True)
            save_checkpoint(nerf, out)
        if args.reload:  # everything below renders the checkpoint as stored, read back
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "nerf.safetensors"
                save_checkpoint(nerf, path)
                nerf = load_checkpoint(path, device=nerf.device)
            row["ckpt"] = cfg.storage_dtype

        # Held-out views as novel views (no depth given): colour and depth error, and the time
        # of a novel view (colour and labels). With per-frame colour corrections, held-out views
        # render with none (the field's average appearance) and, second, with the nearest
        # training frame's.
        val = held_out[:: args.val_every]
        mses, near_mses, derr, times = [], [], [], []
        cm_novel = ConfusionMatrix()
        for f in val:
            t0 = time.perf_counter()
            v = render_image(nerf, f.pose, scene.intrinsics, semantics=labels is not None)
            times.append(time.perf_counter() - t0)
            mses.append(image_mse(v.color, f.color))
            if f.depth is not None and (f.depth > 0).any():
                m = f.depth > 0
                derr.append(float(np.mean(np.abs(v.depth[m] - f.depth[m]))))
            if labels is not None:
                cm_novel.update(v.labels, f.labels["label-nyu40"])
            if nerf.appearance is not None:
                k = nearest_frame(nerf.info.train_poses, f.pose)
                c = render_image(nerf, f.pose, scene.intrinsics, semantics=False, appearance=k)
                near_mses.append(image_mse(c.color, f.color))
        row["val_psnr"] = psnr(float(np.mean(mses)))
        if near_mses:
            row["val_psnr_nearest"] = psnr(float(np.mean(near_mses)))
        row["val_depth_l1_m"] = float(np.mean(derr)) if derr else float("nan")
        row["novel_s_per_view"] = float(np.mean(times))
        # Training views, rendered with their own colour correction.
        if args.train_psnr_every:
            mses = []
            for f in train[:: args.train_psnr_every]:
                i = nerf.info.train_frames.index(f.name)
                v = render_image(nerf, f.pose, scene.intrinsics, semantics=False, appearance=i)
                mses.append(image_mse(v.color, f.color))
            row["train_psnr"] = psnr(float(np.mean(mses)))
        # Pseudo-labels at the training views and at the held-out views, each with its
        # measured depth (what `csa nerf render --scene` and the adaptation do), labels only.
        if labels is not None:
            frames = train[:: args.label_every] + held_out
            cameras = [(f.name, f.pose) for f in frames]
            depths = [f.depth for f in frames]
            # Labels only (what the adaptation renders), then with --time-pairs the same views
            # with colour too (NI+NL's image-label pairs).
            modes = [("labels", False)] + ([("pairs", True)] if args.time_pairs else [])
            rendered = {}
            for key, color in modes:
                t0 = time.perf_counter()
                rendered[key] = render_frames(
                    nerf, cameras, scene.intrinsics, depths=depths, color=color
                )
                row[f"{key}_s_per_view"] = (time.perf_counter() - t0) / len(frames)
            fused = {v.name: v.labels for v in rendered["labels"]}
            if args.time_pairs:
                row["pairs_same_labels"] = all(
                    np.array_equal(v.labels, fused[v.name]) for v in rendered["pairs"]
                )
            row["total_s"] = stats.seconds + row["labels_s_per_view"] * len(scene.frames)
            cm_in, cm_vs_in = ConfusionMatrix(), ConfusionMatrix()
            for f in train[:: args.label_every]:
                cm_in.update(f.labels[labels], f.labels["label-nyu40"])
                cm_vs_in.update(fused[f.name], f.labels[labels])
            row["miou_input"] = cm_in.miou()
            row["miou_rendered"] = label_miou(fused, train[:: args.label_every])
            row["miou_rendered_vs_input"] = cm_vs_in.miou()
            row["miou_val"] = label_miou(fused, held_out)
            row["miou_val_novel"] = cm_novel.miou()
        rows.append(row)
    return rows


COLUMNS = [
    ("preset", "{}"),
    ("ckpt", "{}"),
    ("steps", "{}"),
    ("fit_s", "{:.0f}"),
    ("rays_s", "{:,.0f}"),
    ("samples_s", "{:,.0f}"),
    ("labels_s_per_view", "{:.3f}"),
    ("pairs_s_per_view", "{:.3f}"),
    ("pairs_same_labels", "{}"),
    ("novel_s_per_view", "{:.2f}"),
    ("total_s", "{:.0f}"),
    ("val_psnr", "{:.2f}"),
    ("val_psnr_nearest", "{:.2f}"),
    ("val_depth_l1_m", "{:.3f}"),
    ("train_psnr", "{:.2f}"),
    ("miou_input", "{:.3f}"),
    ("miou_rendered", "{:.3f}"),
    ("miou_rendered_vs_input", "{:.3f}"),
    ("miou_val", "{:.3f}"),
    ("miou_val_novel", "{:.3f}"),
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
    p.add_argument(
        "--holdout",
        default="tail",
        help="held-out frames: tail (last 20%%) or every:N (interleaved)",
    )
    p.add_argument(
        "--color-camera",
        default="none",
        help="7-Scenes colour camera: none (read colour with the depth camera), kinect, estimate",
    )
    p.add_argument("--appearance", default=None, help="per-frame colour correction: none, affine")
    p.add_argument("--storage-dtype", default=None, help="checkpoint dtype: float16 or float32")
    p.add_argument(
        "--reload", action="store_true", help="evaluate the checkpoint written and read back"
    )
    p.add_argument(
        "--set", action="append", default=[], help="config override, e.g. loss.free_space=0.5"
    )
    p.add_argument(
        "--train-psnr-every", type=int, default=0, help="also PSNR of every N-th training view"
    )
    p.add_argument("--val-every", type=int, default=1, help="evaluate every N-th held-out frame")
    p.add_argument(
        "--time-pairs",
        action="store_true",
        help="also time colour and labels of the label views (pairs_s_per_view)",
    )
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
        f"\nscene {args.scene} at {args.size[0]}x{args.size[1]}, holdout {args.holdout}, "
        f"torch {torch.__version__}, {platform.machine()} {torch.get_num_threads()} threads, "
        f"device {args.device}"
    )
    print(table(rows))


if __name__ == "__main__":
    main()
