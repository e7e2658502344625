"""``csa demo``: the main job on the embedded default data, end to end.

Synthesise a pre-training family and a sequence of new scenes from another family, import
the real 7-Scenes kitchen frames when they are present, write label previews and per-scene
statistics, pre-train the light network, then adapt it scene after scene without labels
(NeRF pseudo-labels, joint 2D-3D training, NeRF replay from the memory bank) and print the
pre-trained vs adapted table with the continual metrics. ``--label-fusion`` adds the NeRF's
label fusion on deliberately corrupted labels (the method's 3D half on its own).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from csa_core.adapt.config import MODES, AdaptConfig
from csa_core.adapt.config import PRESETS as ADAPT_PRESETS
from csa_core.cli.args import add_set_argument, positive_int, size_arg

DEFAULT_SEVEN_SCENES = Path("../shared/data/7scenes-kitchen-100")
# Summary columns: key of csa_core.cli.demo_adapt.summary_rows -> printed title.
SUMMARY_COLUMNS = {
    "pretrained": "pre-trained",
    "adabn_only": "AdaBN only",
    "adapted": "adapted (its step)",
    "after_all": "after all steps",
    "prediction_labels": "network labels",
    "nerf_labels": "NeRF labels",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on the embedded default data")
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (replaced)")
    p.add_argument("--size", type=size_arg, default=(128, 96), help="image size of every scene")
    p.add_argument("--frames", type=positive_int, default=60, help="frames per new scene")
    p.add_argument("--pretrain-family", default="apartment")
    p.add_argument("--pretrain-scenes", type=positive_int, default=16)
    p.add_argument(
        "--pretrain-frames", type=positive_int, default=30, help="frames per pre-training room"
    )
    p.add_argument("--pretrain-epochs", type=positive_int, default=20)
    p.add_argument("--target-family", default="office")
    p.add_argument("--target-scenes", type=positive_int, default=3)
    p.add_argument(
        "--mode", default="joint", choices=MODES, help="adaptation mode (default: joint training)"
    )
    p.add_argument(
        "--preset", default="cpu", choices=tuple(ADAPT_PRESETS), help="adaptation budget"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default=None, help="torch device (default: cuda when available)")
    p.add_argument(
        "--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's)"
    )
    p.add_argument(
        "--seven-scenes",
        type=Path,
        default=DEFAULT_SEVEN_SCENES,
        help="7-Scenes sequence to import if present",
    )
    p.add_argument(
        "--label-fusion",
        action="store_true",
        help="also fuse corrupted labels of a new scene in a NeRF",
    )
    p.add_argument(
        "--fusion-size",
        type=size_arg,
        default=(80, 60),
        help="working size of the label-fusion step",
    )
    p.add_argument(
        "--fusion-steps",
        type=positive_int,
        default=600,
        help="NeRF optimisation steps (fast preset)",
    )
    add_set_argument(p, "AdaptConfig of the continual run", "pool_batchnorm=false")
    p.set_defaults(func=run_demo)


def demo_config(args: argparse.Namespace, device: str | None) -> AdaptConfig:
    """The continual run's AdaptConfig: ``--preset``, ``--mode``, every seed ``--seed``, the
    device, then the ``--set`` overrides (the last word)."""
    from csa_core.adapt.config import preset as adapt_preset
    from csa_core.overrides import apply_overrides

    config = adapt_preset(args.preset)
    config.mode = args.mode
    config.seg.seed = config.nerf.seed = config.replay.seed = args.seed
    config.seg.device = device
    return apply_overrides(config, args.set)


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


def _label_fusion(
    scene_dir: Path, out: Path, size: tuple[int, int], steps: int, seed: int, device: str
) -> dict:
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
    from csa_core.data.label_noise import corrupt_labels
    from csa_core.data.scene_io import read_scene
    from csa_core.nerf import fit_semantic_nerf, save_checkpoint

    scene = read_scene(scene_dir, size=size)
    rng = np.random.default_rng(seed)
    for f in scene.frames:
        f.labels["label-noisy"] = corrupt_labels(f.labels["label-nyu40"], rng)
    t0 = time.perf_counter()
    nerf, _ = fit_semantic_nerf(
        scene, "label-noisy", "fast", device=device, steps=steps, progress=True
    )
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, fused = render_at_frames(nerf, scene.train_frames, scene.intrinsics)
    render_s = time.perf_counter() - t0
    noisy = {f.name: f.labels["label-noisy"] for f in scene.train_frames}
    ckpt_bytes = save_checkpoint(nerf, out / f"{scene.name}.nerf.safetensors")
    with atomic_dir(out / "previews", overwrite=True) as tmp:
        for f in scene.train_frames[::8]:
            row = np.concatenate(
                [
                    f.color,
                    colorize(noisy[f.name]),
                    colorize(fused[f.name]),
                    colorize(f.labels["label-nyu40"]),
                ],
                axis=1,
            )
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


def _print_summary(console, result, adabn: list[float], seed: int) -> list[dict]:
    from rich.table import Table

    from csa_core.cli.demo_adapt import summary_rows
    from csa_core.eval.continual import previous_row

    rows = summary_rows(result, adabn)
    table = Table(
        title="validation mIoU (%) of every new scene; labels: mIoU (%) on its training views"
    )
    table.add_column("scene", justify="right")
    for title in SUMMARY_COLUMNS.values():
        table.add_column(title, justify="right")
    for r in rows:
        table.add_row(r["scene"], *(f"{r[k]:.1f}" for k in SUMMARY_COLUMNS))
    mean = {k: float(np.mean([r[k] for r in rows])) for k in SUMMARY_COLUMNS}
    table.add_row("mean", *(f"{mean[k]:.1f}" for k in SUMMARY_COLUMNS), style="bold")
    console.print(table)
    prev = previous_row(result.R)
    console.print(
        "Previous (mean over earlier scenes after each step): "
        + ", ".join("-" if np.isnan(v) else f"{100 * v:.1f}" for v in prev)
    )
    m = result.metrics
    console.print(
        "ACC {:.1f}  A {:.1f}  FWT {:+.1f}  BWT {:+.1f}  (mIoU points)".format(
            *(100 * m[k] for k in ("acc", "a", "fwt", "bwt"))
        )
    )
    gain = mean["after_all"] - mean["pretrained"]
    verdict = "beats" if gain > 0 else "does NOT beat"
    console.print(
        f"the adapted network {verdict} the pre-trained one on the new scenes: "
        f"{mean['after_all']:.1f}% vs {mean['pretrained']:.1f}% mean val mIoU ({gain:+.1f} points)"
    )
    console.print(
        f"This is one run (seed {seed}): "
        "a single run moves by several points with the seed and the machine's "
        "floating-point paths, "
        "so its ordering is not a result. Over seeds: csa experiment multi-step --seeds 0,1,2 "
        "(README.md and benchmarks/results/continual.md report it as mean +- std)."
    )
    return rows


def run_demo(args: argparse.Namespace) -> int:
    import torch
    from rich.console import Console
    from rich.table import Table

    from csa_core.adapt.continual import format_table, run_continual
    from csa_core.adapt.finetune import adabn_only_scores
    from csa_core.atomic_io import write_text_atomic
    from csa_core.cli.demo_adapt import plot_steps, pretrain_network
    from csa_core.data.scene_io import read_scene
    from csa_core.data.sevenscenes import import_7scenes
    from csa_core.data.synth import synthesize
    from csa_core.device import resolve_device

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    console = Console()
    out: Path = args.out
    device = str(resolve_device(args.device))
    config = demo_config(args, device)  # a bad --set fails here, before any work
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    report: dict = {
        "config": {
            k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"
        },
        "device": device,
        "torch_threads": torch.get_num_threads(),
        "scenes": {},
        "seconds": {},
    }

    console.rule("1. synthetic rooms")
    pre = synthesize(
        out / "scenes" / "pretrain",
        scenes=args.pretrain_scenes,
        frames=args.pretrain_frames,
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
    report["seconds"]["data"] = time.perf_counter() - t0

    console.rule("3. previews and statistics")
    table = Table(title="scenes")
    for col in ("scene", "role", "frames (train/val)", "depth measured", "classes"):
        table.add_column(col)
    scenes = {}
    for path, role in roles.items():
        scene = read_scene(path)
        scenes[path] = scene
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

    if args.label_fusion:
        console.rule("NeRF label fusion on a new scene")
        fusion = _label_fusion(
            new[0], out / "fusion", args.fusion_size, args.fusion_steps, args.seed, device
        )
        report["label_fusion"] = fusion
        ft = Table(
            title=f"label fusion on {fusion['scene']} ({fusion['train_views']} training views at "
            f"{fusion['size'][0]}x{fusion['size'][1]}, mIoU vs ground truth)"
        )
        for col in (
            "per-frame corrupted labels",
            "NeRF-rendered labels",
            "fit",
            "render",
            "checkpoint",
        ):
            ft.add_column(col)
        ft.add_row(
            f"{fusion['noisy_miou'] * 100:.1f}%",
            f"{fusion['fused_miou'] * 100:.1f}%",
            f"{fusion['fit_seconds']:.0f} s",
            f"{fusion['render_seconds']:.0f} s",
            f"{fusion['checkpoint_bytes'] / 1e6:.2f} MB",
        )
        console.print(ft)
        console.print(
            f"fusion previews (colour | corrupted | fused | truth) in {out / 'fusion' / 'previews'}"
        )

    console.rule(f"4. pre-training the light network on {len(pre)} {args.pretrain_family} rooms")
    t = time.perf_counter()
    pre_scenes = [scenes[p] for p in pre]
    target_scenes = [scenes[p] for p in new]
    model, info = pretrain_network(
        pre_scenes,
        args.size,
        args.pretrain_epochs,
        args.seed,
        device,
        out / "pretrained.safetensors",
    )
    report["pretrain"] = info
    report["seconds"]["pretrain"] = time.perf_counter() - t
    console.print(
        f"best epoch {info['best_epoch']}: {100 * (info['best_val_miou'] or 0):.1f}% mIoU on the "
        f"{args.pretrain_family} rooms' validation views; checkpoint {info['checkpoint']}"
    )

    console.rule(
        f"5. continual adaptation to {len(new)} {args.target_family} rooms "
        f"({args.mode}, NeRF replay)"
    )
    t = time.perf_counter()
    adabn = adabn_only_scores(model, target_scenes, seed=config.seg.seed, device=config.seg.device)
    result = run_continual(
        model, target_scenes, config, out / "continual", pretrain_scenes=pre_scenes
    )
    report["seconds"]["adapt"] = time.perf_counter() - t
    console.print(format_table(result))
    report["summary"] = _print_summary(console, result, adabn, args.seed)
    report["continual"] = {
        "results": str(out / "continual" / "results.json"),
        "metrics": result.metrics,
    }
    plot = out / "plots" / "miou_per_step.png"
    plot.parent.mkdir(parents=True, exist_ok=True)
    plot_steps(plot, result)

    report["seconds"]["total"] = time.perf_counter() - t0
    write_text_atomic(out / "report.json", json.dumps(report, indent=2, default=float))
    console.print(
        f"scenes in {out / 'scenes'}, previews in {out / 'previews'}, plot {plot}, adapted model "
        f"{out / 'continual' / 'model.safetensors'}, memory bank {out / 'continual' / 'memory'}, "
        f"report {out / 'report.json'} ({report['seconds']['total']:.0f} s)"
    )
    return 0
