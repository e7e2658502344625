"""``csa demo``: the main job on the embedded default data, end to end.

Today: synthesise a pre-training family and a sequence of new scenes from another family,
import the real 7-Scenes kitchen frames when they are present, write label previews and
per-scene statistics, and fuse view-inconsistent per-frame labels of a new scene in a
Semantic-NeRF (the method's 3D half). The continual adaptation step is still to come.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from csa_core.cli.args import positive_int, size_arg

DEFAULT_SEVEN_SCENES = Path("../shared/data/7scenes-kitchen-100")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on the embedded default data")
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (replaced)")
    p.add_argument("--size", type=size_arg, default=(160, 120))
    p.add_argument("--frames", type=positive_int, default=60)
    p.add_argument("--pretrain-family", default="apartment")
    p.add_argument("--pretrain-scenes", type=positive_int, default=4)
    p.add_argument("--target-family", default="office")
    p.add_argument("--target-scenes", type=positive_int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--seven-scenes",
        type=Path,
        default=DEFAULT_SEVEN_SCENES,
        help="7-Scenes sequence to import if present",
    )
    p.add_argument("--fusion-size", type=size_arg, default=(80, 60), help="working size of the NeRF label-fusion step")
    p.add_argument("--fusion-steps", type=positive_int, default=600, help="NeRF optimisation steps (fast preset)")
    p.add_argument("--no-fusion", action="store_true", help="skip the NeRF label-fusion step")
    p.set_defaults(func=run_demo)


def _scene_stats(scene) -> dict:
    from csa_core.data.nyu40 import CLASS_NAMES

    stats: dict = {"frames": len(scene), "train": scene.num_train, "val": len(scene.val_frames)}
    depth = (
        np.stack([f.depth for f in scene.frames if f.depth is not None])
        if scene.frames[0].depth is not None
        else None
    )
    if depth is not None:
        stats["depth_measured"] = float((depth > 0).mean())
        stats["depth_median_m"] = float(np.median(depth[depth > 0]))
    if "label-nyu40" in scene.label_folders:
        labs = np.stack([f.labels["label-nyu40"] for f in scene.frames])
        counts = np.bincount(labs.ravel(), minlength=41)
        stats["classes"] = [CLASS_NAMES[i] for i in np.flatnonzero(counts[1:]) + 1]
    return stats


def _previews(scene, out: Path, every: int = 15) -> int:
    from csa_core.atomic_io import atomic_dir
    from csa_core.data.label_images import save_preview

    frames = scene.frames[::every]
    with atomic_dir(out, overwrite=True) as tmp:
        for f in frames:
            if "label-nyu40" in f.labels:
                save_preview(tmp / f"{f.name}.png", f.color, f.labels["label-nyu40"])
            else:
                save_preview(
                    tmp / f"{f.name}.png",
                    f.color,
                    np.zeros(f.color.shape[:2], np.uint8),
                    legend=False,
                )
    return len(frames)


def _label_fusion(scene_dir: Path, out: Path, size: tuple[int, int], steps: int, seed: int) -> dict:
    """Corrupt a scene's labels frame by frame, fuse them in a NeRF, score both against truth.

    The corruption (wrong-class blobs, partly swapped objects, ragged edges, different in
    every frame) stands in for a network's view-inconsistent predictions, so the gain of
    multi-view fusion is measured without a network in the loop.
    """
    import cv2
    import numpy as np

    from csa_core.adapt.pseudo_labels import label_miou, render_at_frames
    from csa_core.atomic_io import atomic_dir
    from csa_core.data.label_images import colorize
    from csa_core.data.scene_io import read_scene
    from csa_core.nerf import fit_semantic_nerf, save_checkpoint
    from csa_core.nerf.label_noise import corrupt_labels

    scene = read_scene(scene_dir, size=size)
    rng = np.random.default_rng(seed)
    for f in scene.frames:
        f.labels["label-noisy"] = corrupt_labels(f.labels["label-nyu40"], rng)
    t0 = time.perf_counter()
    nerf, _ = fit_semantic_nerf(scene, "label-noisy", "fast", steps=steps, progress=True)
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, fused = render_at_frames(nerf, scene.train_frames, scene.intrinsics)
    render_s = time.perf_counter() - t0
    noisy = {f.name: f.labels["label-noisy"] for f in scene.train_frames}
    ckpt_bytes = save_checkpoint(nerf, out / f"{scene.name}.nerf.safetensors")
    with atomic_dir(out / "previews", overwrite=True) as tmp:
        for f in scene.train_frames[::8]:
            row = np.concatenate([f.color, colorize(noisy[f.name]), colorize(fused[f.name]), colorize(f.labels["label-nyu40"])], axis=1)
            cv2.imwrite(str(tmp / f"{f.name}.png"), cv2.cvtColor(row, cv2.COLOR_RGB2BGR))
    return {
        "scene": scene.name,
        "size": list(size),
        "train_views": scene.num_train,
        "steps": steps,
        "noisy_miou": label_miou(noisy, scene),
        "fused_miou": label_miou(fused, scene),
        "fit_seconds": fit_s,
        "render_seconds": render_s,
        "checkpoint_bytes": int(ckpt_bytes),
    }


def run_demo(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from csa_core.atomic_io import write_text_atomic
    from csa_core.data.scene_io import read_scene
    from csa_core.data.sevenscenes import import_7scenes
    from csa_core.data.synth import synthesize

    console = Console()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    report: dict = {
        "config": {
            k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"
        },
        "scenes": {},
    }

    console.rule("1. synthetic rooms")
    pre = synthesize(
        out / "scenes" / "pretrain",
        scenes=args.pretrain_scenes,
        frames=args.frames,
        size=args.size,
        family=args.pretrain_family,
        seed=args.seed,
        overwrite=True,
    )
    new = synthesize(
        out / "scenes" / "target",
        scenes=args.target_scenes,
        frames=args.frames,
        size=args.size,
        family=args.target_family,
        seed=args.seed + 1000,
        overwrite=True,
    )
    roles = {p: "pretrain" for p in pre} | {p: "target" for p in new}

    console.rule("2. real frames (7-Scenes)")
    if args.seven_scenes.is_dir():
        kitchen = out / "scenes" / "real" / "7scenes-kitchen"
        import_7scenes(args.seven_scenes, kitchen, size=args.size, overwrite=True)
        roles[kitchen] = "real (no labels)"
    else:
        console.print(
            f"[yellow]{args.seven_scenes} not found: skipping the real-data import[/yellow]"
        )

    console.rule("3. previews and statistics")
    table = Table(title="scenes")
    for col in ("scene", "role", "frames (train/val)", "depth measured", "classes"):
        table.add_column(col)
    for path, role in roles.items():
        scene = read_scene(path)
        stats = _scene_stats(scene) | {"role": role, "path": str(path)}
        stats["previews"] = _previews(scene, out / "previews" / scene.name)
        report["scenes"][scene.name] = stats
        table.add_row(
            scene.name,
            role,
            f"{stats['frames']} ({stats['train']}/{stats['val']})",
            f"{stats.get('depth_measured', 0) * 100:.0f}%",
            str(len(stats.get("classes", []))),
        )
    console.print(table)

    if not args.no_fusion:
        console.rule("4. NeRF label fusion on a new scene")
        fusion = _label_fusion(new[0], out / "fusion", args.fusion_size, args.fusion_steps, args.seed)
        report["label_fusion"] = fusion
        ft = Table(title=f"label fusion on {fusion['scene']} ({fusion['train_views']} training views at "
                         f"{fusion['size'][0]}x{fusion['size'][1]}, mIoU vs ground truth)")
        for col in ("per-frame corrupted labels", "NeRF-rendered labels", "fit", "render", "checkpoint"):
            ft.add_column(col)
        ft.add_row(f"{fusion['noisy_miou'] * 100:.1f}%", f"{fusion['fused_miou'] * 100:.1f}%",
                   f"{fusion['fit_seconds']:.0f} s", f"{fusion['render_seconds']:.0f} s",
                   f"{fusion['checkpoint_bytes'] / 1e6:.2f} MB")
        console.print(ft)
        console.print(f"fusion previews (colour | corrupted | fused | truth) in {out / 'fusion' / 'previews'}")

    report["seconds"] = time.perf_counter() - t0
    write_text_atomic(out / "report.json", json.dumps(report, indent=2))
    console.print(
        f"scenes in {out / 'scenes'}, previews in {out / 'previews'}, report {out / 'report.json'} "
        f"({report['seconds']:.0f} s)"
    )
    return 0
