"""``csa adapt``: adapt a segmentation network to new scenes without their labels.

One scene is a one-step adaptation (a before/after table when the scene has ground truth);
several are a continual run over the scenes in the order given (the R matrix and ACC, A, FWT,
BWT; then every scene needs ground truth, since R is scored on it). Either way ``--out`` gets
the adapted checkpoint (``model.safetensors``, its card pointing at the input checkpoint),
``results.json`` with the full config, and for our method the NeRF memory bank (``memory/``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from csa_core.cli.args import add_set_argument, positive_int, size_arg

if TYPE_CHECKING:
    from csa_core.adapt.config import AdaptConfig

DEFAULT_PRESET = "cpu"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "adapt",
        help="adapt a network to new scenes without their labels (one scene: one step; "
        "several: a continual run)",
    )
    p.add_argument(
        "scenes", type=Path, nargs="+", metavar="SCENE_DIR", help="scene folders, in visiting order"
    )
    p.add_argument(
        "--model", type=Path, required=True, metavar="CKPT", help="segmentation checkpoint to adapt"
    )
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--preset",
        default=DEFAULT_PRESET,
        help="paper (the paper's configuration; GPU-sized, runs slowly on a CPU), cpu (ours) "
        f"or tiny (tests) (default {DEFAULT_PRESET})",
    )
    p.add_argument(
        "--mode", default=None, help="our method's mode: gi_nl, ni_nl or joint (default joint)"
    )
    p.add_argument(
        "--method",
        default="ours",
        help="ours, or a baseline: mapping, cotta, finetune (default ours)",
    )
    p.add_argument(
        "--pretrain-scenes",
        type=Path,
        nargs="+",
        default=[],
        metavar="SCENE_DIR",
        help="labelled pre-training scenes: 10%% of their frames are replayed",
    )
    p.add_argument(
        "--size",
        type=size_arg,
        default=None,
        help="working size WxH (default: the size the network was trained at)",
    )
    p.add_argument(
        "--adabn",
        choices=("on", "off"),
        default=None,
        help="re-estimate BatchNorm statistics on each scene's camera images, for any method "
        "(default: the preset's, on)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of every random step (default 0)")
    p.add_argument(
        "--device", default=None, help="cpu, cuda, cuda:1 ... (default: cuda if available)"
    )
    p.add_argument("--threads", type=positive_int, default=None, help="CPU threads for torch")
    p.add_argument(
        "--overwrite", action="store_true", help="replace the results of an earlier run in --out"
    )
    add_set_argument(p, "AdaptConfig", "collapse.enabled=false or replay.buffer_size=24")
    p.set_defaults(func=run_adapt)


def _check_out(out: Path, overwrite: bool) -> None:
    """Refuse to mix two runs in one folder; with ``overwrite`` drop the old memory bank
    (its NeRFs would otherwise be replayed as if this run had seen those scenes)."""
    from csa_core.errors import CSAInputError

    old = [out / n for n in ("results.json", "model.safetensors", "memory") if (out / n).exists()]
    if old and not overwrite:
        raise CSAInputError(out, "output already exists (pass --overwrite to replace it)")
    if overwrite and (out / "memory").is_dir():
        shutil.rmtree(out / "memory")


def _table_one_step(record: dict[str, Any]) -> str:
    from csa_core.experiments.report import markdown_table, pct

    before, after = record["before"], record["after"]
    if not before:
        return f"{record['scene']}: no ground truth, nothing to score"
    rows = [
        [what, pct(d.get("val", float("nan"))), pct(d.get("train", float("nan")))]
        for what, d in (("before", before), ("after", after))
    ]
    lines = [markdown_table([record["scene"], "val mIoU %", "train mIoU %"], rows)]
    labels = []
    if record.get("prediction_miou") is not None:
        labels.append(f"network {pct(record['prediction_miou'])}%")
    if record.get("pseudo_label_miou") is not None:
        labels.append(f"pseudo-labels {pct(record['pseudo_label_miou'])}%")
    if labels:
        lines.append("\nlabels on the training views: " + ", ".join(labels))
    return "\n".join(lines)


def adapt_config(args: argparse.Namespace) -> AdaptConfig:
    """The run's config: the preset, every seed set to ``--seed``, ``--mode``, ``--adabn``
    and ``--device``, then the ``--set`` overrides (the last word); an input error names a
    bad flag or override before anything is loaded."""
    from csa_core.adapt.config import MODES, PRESETS, preset
    from csa_core.errors import CSAInputError
    from csa_core.experiments.inputs import seeded
    from csa_core.overrides import apply_overrides

    if args.preset not in PRESETS:
        raise CSAInputError(
            "--preset", f"unknown preset {args.preset!r} (choose from {', '.join(PRESETS)})"
        )
    if args.mode is not None and args.mode not in MODES:
        raise CSAInputError(
            "--mode", f"unknown mode {args.mode!r} (choose from {', '.join(MODES)})"
        )
    config = seeded(preset(args.preset), args.seed)
    config.mode = args.mode or config.mode
    if args.adabn is not None:
        config.adabn = args.adabn == "on"
    config.seg.device = args.device
    return apply_overrides(config, args.set)


def run_adapt(args: argparse.Namespace) -> int:
    import torch

    from csa_core.adapt.continual import format_table, run_continual
    from csa_core.adapt.methods import METHODS, check_method, pretrain_context
    from csa_core.adapt.step import one_step
    from csa_core.atomic_io import write_text_atomic
    from csa_core.data.scene_io import read_scene
    from csa_core.device import resolve_device
    from csa_core.experiments.report import jsonable
    from csa_core.seg.checkpoint import load_checkpoint, save_checkpoint
    from csa_core.seg.config import paper_network_note

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    config = adapt_config(args)
    method = check_method(args.method, METHODS, "--method")
    _check_out(args.out, args.overwrite)
    model, card = load_checkpoint(args.model, device=resolve_device(args.device))
    size = args.size or (tuple(card.input_size) if card.input_size else None)
    note = paper_network_note(args.preset, card.arch, size)
    if note:
        print(note, file=sys.stderr)
    scenes = [read_scene(p, size=size) for p in args.scenes]
    pretrain_scenes = [read_scene(p, size=size) for p in args.pretrain_scenes]
    args.out.mkdir(parents=True, exist_ok=True)
    checkpoint = args.out / "model.safetensors"
    if len(scenes) == 1:
        pretrain, prior = pretrain_context(pretrain_scenes, config)
        record, reported = one_step(model, scenes[0], config, method, args.out, pretrain, prior)
        child = card.child(
            train_config={
                "task": "one-step",
                "method": method,
                "scene": scenes[0].name,
                "adapt": config.to_dict(),
            },
            metrics={"before": record["before"], "after": record["after"]},
        )
        save_checkpoint(checkpoint, reported, child)  # type: ignore[arg-type]
        doc = {
            "task": "one-step",
            "model": str(args.model),
            "scenes": [str(p) for p in args.scenes],
            "config": {
                **config.to_dict(),
                "method": method,
                "method_settings": record["method_settings"],
                "pretrain_scenes": [str(p) for p in args.pretrain_scenes],
                "size": list(size) if size else None,
            },
            "result": record,
        }
        write_text_atomic(args.out / "results.json", json.dumps(jsonable(doc), indent=2) + "\n")
        print(_table_one_step(record))
    else:
        result = run_continual(
            model,
            scenes,
            config,
            args.out,
            pretrain_scenes,
            save_model=True,
            method=method,
            parent=card,
        )
        print(format_table(result))
    print(
        f"\n{checkpoint}: adapted network ({method}); {args.out / 'results.json'}: scores and "
        "config"
    )
    return 0
