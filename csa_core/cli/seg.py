"""``csa seg``: pre-train segmentation networks, label scenes with them and score them."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from csa_core.cli.args import add_set_argument, positive_int, size_arg

if TYPE_CHECKING:
    from csa_core.seg.config import PretrainConfig


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {v}")
    return v


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device", default=None, help="cpu, cuda, cuda:1 ... (default: cuda if available)"
    )
    p.add_argument(
        "--threads",
        type=positive_int,
        default=None,
        help="CPU threads for torch (default: torch's choice)",
    )
    p.add_argument(
        "--batch-size", type=positive_int, default=None, help="images per batch (default 8)"
    )


def register(sub: argparse._SubParsersAction) -> None:
    from csa_core.seg.config import ARCH_NAMES, PRETRAIN_PRESETS, SCHEDULES, pretrain_preset

    pre = pretrain_preset("cpu")
    defaults = pre.train
    paper = pretrain_preset("paper")
    p = sub.add_parser("seg", help="pre-train, run and score segmentation networks")
    cmds = p.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)

    t = cmds.add_parser("pretrain", help="train a network from scratch on labelled scene folders")
    t.add_argument(
        "scenes",
        type=Path,
        nargs="+",
        metavar="SCENE_DIR",
        help="labelled scene folders to train on",
    )
    t.add_argument("--out", type=Path, required=True, help="checkpoint to write (.safetensors)")
    t.add_argument(
        "--preset",
        choices=tuple(PRETRAIN_PRESETS),
        default="cpu",
        help=f"network, size and training settings: cpu (ours: {pre.arch} at "
        f"{pre.size[0]}x{pre.size[1]}) or paper ({paper.arch} at {paper.size[0]}x"
        f"{paper.size[1]}, the official pre-training); the options below override it "
        "(default cpu)",
    )
    t.add_argument(
        "--arch", choices=ARCH_NAMES, default=None, help=f"network (cpu preset: {pre.arch})"
    )
    t.add_argument(
        "--epochs", type=positive_int, default=None, help=f"(cpu preset: {defaults.epochs})"
    )
    t.add_argument(
        "--lr",
        type=_positive_float,
        default=None,
        help=f"initial Adam learning rate (cpu preset: {defaults.lr})",
    )
    t.add_argument(
        "--schedule",
        choices=SCHEDULES,
        default=None,
        help=f"learning-rate decay (cpu preset: {defaults.schedule})",
    )
    t.add_argument(
        "--size",
        type=size_arg,
        default=None,
        help=f"working size WxH (cpu preset: {pre.size[0]}x{pre.size[1]})",
    )
    t.add_argument(
        "--labels",
        default=pre.label_folder,
        help=f"label folder to learn from (default {pre.label_folder})",
    )
    t.add_argument("--every", type=positive_int, default=1, help="keep every N-th frame")
    t.add_argument(
        "--val-scenes",
        type=Path,
        nargs="+",
        default=None,
        metavar="SCENE_DIR",
        help="score on these scenes' validation views and train on all views of SCENE_DIRs "
        "(default: train on each scene's training views, score on its validation views)",
    )
    t.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="local safetensors file of torchvision-named weights to start from",
    )
    t.add_argument(
        "--no-augment",
        action="store_true",
        help="train without flips, rotations, crops and colour jitter",
    )
    t.add_argument("--seed", type=int, default=defaults.seed)
    t.add_argument("--overwrite", action="store_true")
    add_set_argument(t, "PretrainConfig", "train.final_lr=1e-6 or train.schedule=poly")
    _common(t)
    t.set_defaults(func=_pretrain)

    r = cmds.add_parser(
        "predict",
        help="label a scene's frames with a checkpoint (a label folder at colour resolution)",
    )
    r.add_argument("checkpoint", type=Path)
    r.add_argument("scene", type=Path)
    dest = r.add_mutually_exclusive_group(required=True)
    dest.add_argument("--out-labels", metavar="NAME", help="write the label folder SCENE/NAME")
    dest.add_argument("--out", type=Path, help="write the label folder here instead")
    r.add_argument(
        "--split",
        choices=("all", "train", "val"),
        default="all",
        help="frames to label (default all)",
    )
    r.add_argument(
        "--size",
        type=size_arg,
        default=None,
        help="network input size WxH (default: the size it was trained at)",
    )
    r.add_argument(
        "--adabn",
        action="store_true",
        help="re-estimate BatchNorm statistics on the frames first (AdaBN)",
    )
    r.add_argument("--overwrite", action="store_true")
    _common(r)
    r.set_defaults(func=_predict)

    e = cmds.add_parser("eval", help="mIoU of a checkpoint on scenes' validation views")
    e.add_argument("checkpoint", type=Path)
    e.add_argument("scenes", type=Path, nargs="+", metavar="SCENE")
    e.add_argument(
        "--split",
        choices=("val", "train", "all"),
        default="val",
        help="views to score (default val)",
    )
    e.add_argument(
        "--labels",
        default=pre.label_folder,
        help=f"ground-truth label folder (default {pre.label_folder})",
    )
    e.add_argument(
        "--size",
        type=size_arg,
        default=None,
        help="working size WxH (default: the size it was trained at)",
    )
    e.add_argument(
        "--adabn",
        action="store_true",
        help="first re-estimate BatchNorm statistics on each scene's training views (AdaBN)",
    )
    e.add_argument("--per-class", action="store_true", help="also print per-class IoU")
    e.add_argument("--json", type=Path, default=None, help="also write the scores as JSON")
    _common(e)
    e.set_defaults(func=_eval)


def _setup_threads(args: argparse.Namespace) -> None:
    if args.threads is not None:
        import torch

        torch.set_num_threads(args.threads)


def pretrain_config(args: argparse.Namespace) -> PretrainConfig:
    """The pre-training config of ``csa seg pretrain``: the ``--preset``'s, with the options
    given on the command line in place of its values, then the ``--set`` overrides."""
    from dataclasses import replace

    from csa_core.overrides import apply_overrides
    from csa_core.seg.config import pretrain_preset

    config = pretrain_preset(args.preset)
    config.arch = args.arch or config.arch
    config.size = args.size or config.size
    config.label_folder = args.labels
    t = config.train
    config.train = replace(
        t,
        epochs=args.epochs or t.epochs,
        batch_size=args.batch_size or t.batch_size,
        lr=args.lr or t.lr,
        schedule=args.schedule or t.schedule,
        seed=args.seed,
        device=args.device,
    )
    if args.no_augment:
        config.augment = None
    return apply_overrides(config, getattr(args, "set", None) or [])


def _pretrain(args: argparse.Namespace) -> int:

    from csa_core.data.scene import Scene
    from csa_core.data.scene_io import read_scene
    from csa_core.errors import CSAInputError
    from csa_core.seg.pretraining import pretrain

    _setup_threads(args)
    if args.out.exists() and not args.overwrite:
        raise CSAInputError(args.out, "output already exists (pass --overwrite to replace it)")
    config = pretrain_config(args)

    def read(paths: list[Path]) -> list[Scene]:
        return [
            read_scene(p, size=config.size, labels=[args.labels], every=args.every) for p in paths
        ]

    val = read(args.val_scenes) if args.val_scenes else None
    _, result = pretrain(
        read(args.scenes), config, out=args.out, val_scenes=val, weights=args.weights
    )
    if result.best_score is None:
        score = "no validation score"
    else:
        per_set = ", ".join(f"{k} {100 * v:.1f}" for k, v in result.best_val_miou.items())
        score = f"val mIoU {100 * result.best_score:.1f}% ({per_set})"
    rate = result.images_seen / max(result.seconds, 1e-9)
    print(f"{args.out}: best epoch {result.best_epoch}/{len(result.history)}, {score}")
    print(f"trained on {result.images_seen} images in {result.seconds:.0f} s ({rate:.1f} images/s)")
    return 0


def _load(args: argparse.Namespace):
    from csa_core.device import resolve_device
    from csa_core.seg.checkpoint import load_checkpoint

    _setup_threads(args)
    model, card = load_checkpoint(args.checkpoint, device=resolve_device(args.device))
    size = args.size or (tuple(card.input_size) if card.input_size else None)
    return model, card, size


def _predict(args: argparse.Namespace) -> int:
    from csa_core.data.scene_io import RESERVED_FOLDERS, read_scene, write_label_folder
    from csa_core.errors import CSAInputError
    from csa_core.seg.adabn import adapt_batchnorm
    from csa_core.seg.predict import predict_scene

    if args.out_labels is not None and (
        args.out_labels in RESERVED_FOLDERS
        or not args.out_labels
        or "/" in args.out_labels
        or args.out_labels.startswith(".")
    ):
        raise CSAInputError(
            "--out-labels", f"{args.out_labels!r} is not a usable label folder name"
        )
    model, card, size = _load(args)
    scene = read_scene(args.scene, labels=[])
    frames = scene.split(args.split)
    batch = args.batch_size or 8
    if args.adabn:
        adapt_batchnorm(
            model, [f.color for f in frames], batch_size=max(2, batch), device=args.device
        )
    labels = predict_scene(
        model, scene, args.split, batch_size=batch, device=args.device, size=size
    )
    dest = args.out if args.out is not None else args.scene / args.out_labels
    write_label_folder(dest, labels, overwrite=args.overwrite)
    w, h = scene.size
    print(f"{dest}: {len(labels)} label maps at {w}x{h} from {args.checkpoint} ({card.arch})")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from csa_core.atomic_io import write_text_atomic
    from csa_core.data.scene_io import read_scene
    from csa_core.eval.miou import format_miou_table
    from csa_core.seg.adabn import adapt_batchnorm
    from csa_core.seg.predict import evaluate_scene

    model, card, size = _load(args)
    batch = args.batch_size or 8
    state = {k: v.clone() for k, v in model.state_dict().items()}
    rows = []
    for path in args.scenes:
        scene = read_scene(path, size=size, labels=[args.labels])
        if args.adabn:
            model.load_state_dict(state)
            adapt_batchnorm(
                model,
                [f.color for f in scene.train_frames],
                batch_size=max(2, batch),
                device=args.device,
            )
        summary = evaluate_scene(
            model, scene, args.split, args.labels, batch_size=batch, device=args.device
        ).summary()
        rows.append((scene.name, len(scene.split(args.split)), summary))
        if args.per_class:
            print(format_miou_table(summary, title=f"{scene.name} ({args.split} views)"))
            print()
    width = max(len("scene"), *(len(name) for name, _, _ in rows))
    print(f"{'scene':<{width}}  {'views':>5}  {'mIoU (%)':>8}  {'pixel acc (%)':>13}")
    for name, n, s in rows:
        print(f"{name:<{width}}  {n:>5}  {100 * s['miou']:8.1f}  {100 * s['pixel_accuracy']:13.1f}")
    if len(rows) > 1:
        mean = sum(s["miou"] for _, _, s in rows) / len(rows)
        print(f"{'mean':<{width}}  {'':>5}  {100 * mean:8.1f}")
    if args.json is not None:
        report = {
            "checkpoint": str(args.checkpoint),
            "arch": card.arch,
            "split": args.split,
            "adabn": args.adabn,
            "size": list(size) if size else None,
        }
        report["scenes"] = {name: s for name, _, s in rows}
        write_text_atomic(args.json, json.dumps(report, indent=2, default=float))
    return 0
