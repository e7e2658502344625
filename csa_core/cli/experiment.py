"""``csa experiment``: the paper's experiments on a scene sequence, as tables, CSV and plots.

``pseudo-labels`` (label quality of network, Mapping and NeRF), ``one-step`` (each scene on
its own, every mode and baseline), ``multi-step`` (the continual protocol per method) and
``footprint`` (memory per method after 1..T scenes). Scenes need ``label-nyu40`` ground
truth: it is read only to score. Outputs go to ``--out``: ``<name>.md``, ``<name>.csv``,
``config.json`` (one entry per experiment: seeds, inputs, versions, every run's config), PNG
plots, and the runs' own files under ``runs/<name>/``. ``--set KEY=VALUE`` changes a field of
every run's ``AdaptConfig`` after the preset and the other flags.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from csa_core.cli.args import add_set_argument, positive_int, size_arg


def register(sub: argparse._SubParsersAction) -> None:
    from csa_core.experiments import EXPERIMENTS

    p = sub.add_parser(
        "experiment", help="run the paper's experiments: tables (Markdown, CSV) and plots"
    )
    cmds = p.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    helps = {
        "pseudo-labels": "mIoU of network, Mapping and NeRF labels on the training views",
        "one-step": "validation mIoU before/after adapting to each scene, per mode and baseline",
        "multi-step": "continual run per method: Adapt/Previous per step, ACC, A, FWT, BWT",
        "footprint": "bytes each method keeps after 1..T scenes",
    }
    for name in EXPERIMENTS:
        e = cmds.add_parser(name, help=helps[name])
        e.add_argument(
            "--model", type=Path, required=True, metavar="CKPT", help="pre-trained checkpoint"
        )
        e.add_argument(
            "--scenes",
            type=Path,
            nargs="+",
            required=True,
            metavar="SCENE_DIR",
            help="the sequence, in order (with label-nyu40 ground truth for scoring)",
        )
        e.add_argument(
            "--pretrain-scenes",
            type=Path,
            nargs="+",
            default=[],
            metavar="SCENE_DIR",
            help="labelled pre-training scenes, replayed (10%% of their frames)",
        )
        e.add_argument("--out", type=Path, required=True, help="output folder")
        e.add_argument("--preset", default="cpu", help="paper, cpu or tiny (default cpu)")
        e.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
        e.add_argument(
            "--size",
            type=size_arg,
            default=None,
            help="working size WxH (default: the size the network was trained at)",
        )
        e.add_argument(
            "--device", default=None, help="cpu, cuda, cuda:1 ... (default: cuda if available)"
        )
        e.add_argument("--threads", type=positive_int, default=None, help="CPU threads for torch")
        if name in ("one-step", "multi-step"):
            e.add_argument(
                "--methods",
                default=None,
                help="comma-separated methods (default: all; see the table's method column)",
            )
        if name == "multi-step":
            e.add_argument(
                "--mode",
                default=None,
                help="our method's mode: gi_nl, ni_nl, joint (default joint)",
            )
            e.add_argument(
                "--adabn",
                default=None,
                choices=("on", "off", "both"),
                help="every method with AdaBN (BatchNorm statistics re-estimated on each "
                "scene's camera images), without, or both side by side (default: the preset's, on)",
            )
            e.add_argument(
                "--resume",
                action="store_true",
                help="reuse the runs an earlier invocation with the same --out finished (same "
                "scenes, method, config and pre-trained network); do the others",
            )
        add_set_argument(
            e, "AdaptConfig of every run", "collapse.enabled=false or replay.buffer_size=24"
        )
        e.set_defaults(func=run_experiment_command)


def run_experiment_command(args: argparse.Namespace) -> int:
    import torch

    from csa_core.experiments import allowed_methods, run_experiment
    from csa_core.experiments.inputs import load_inputs, parse_seeds
    from csa_core.seg.config import paper_network_note

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    name = args.experiment
    methods_text = getattr(args, "methods", None)
    methods = (
        [m.strip() for m in methods_text.split(",") if m.strip()]
        if methods_text is not None
        else None
    )
    inputs = load_inputs(
        args.model,
        args.scenes,
        args.out,
        preset_name=args.preset,
        seeds=parse_seeds(args.seeds),
        pretrain_paths=args.pretrain_scenes,
        size=args.size,
        device=args.device,
        mode=getattr(args, "mode", None),
        methods=methods,
        allowed_methods=allowed_methods(name),
        adabn=getattr(args, "adabn", None),
        overrides=args.set,
        resume=getattr(args, "resume", False),
    )
    note = paper_network_note(args.preset, inputs.card.arch, inputs.size)
    if note:
        print(note, file=sys.stderr)
    report, written = run_experiment(name, inputs)
    print(report.markdown)
    print()
    for path in written:
        print(f"wrote {path}")
    return 0
