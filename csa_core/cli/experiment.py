"""``csa experiment``: the paper's experiments on a scene sequence, as tables, CSV and plots.

``pseudo-labels`` (label quality of network, Mapping and NeRF), ``one-step`` (each scene on
its own, every mode and baseline), ``multi-step`` (the continual protocol per method) and
``footprint`` (memory per method after 1..T scenes). Scenes need ``label-nyu40`` ground
truth: it is read only to score. Outputs go to ``--out``: ``<name>.md``, ``<name>.csv``,
``config.json`` (one entry per experiment: seeds, inputs, versions, every run's config), PNG
plots, and the runs' own files under ``runs/<name>/``. ``--set KEY=VALUE`` changes a field of
every run's ``AdaptConfig`` after the preset and the other flags. ``paper`` runs all of them
the paper has tables for (Tab. 1-3, the ablations, the NeRF frameworks) into one report,
resuming the units a previous invocation finished (csa_core/experiments/paper.py).
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
        if name in ("one-step", "multi-step"):
            e.add_argument(
                "--resume",
                action="store_true",
                help="reuse the runs an earlier invocation with the same --out finished (same "
                "scenes, method, config and pre-trained network); do the others",
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
        add_set_argument(
            e, "AdaptConfig of every run", "collapse.enabled=false or replay.buffer_size=24"
        )
        e.set_defaults(func=run_experiment_command)
    register_paper(cmds)


# ``csa experiment paper`` without scene folders makes the demo's (csa_core/cli/demo.py):
# office rooms to adapt to, apartment rooms to pre-train the light network on and replay.
DEMO_TARGET_FAMILY = "office"
DEMO_PRETRAIN_FAMILY = "apartment"
DEMO_SIZE = (128, 96)


def register_paper(cmds: argparse._SubParsersAction) -> None:
    from csa_core.experiments import PAPER_FRAMEWORKS as FRAMEWORKS
    from csa_core.experiments import PAPER_TABLES as TABLES

    e = cmds.add_parser(
        "paper",
        help="every table of the paper (Tab. 1-3, ablations, NeRF frameworks) in one report",
    )
    e.add_argument(
        "scenes",
        type=Path,
        nargs="*",
        metavar="SCENE_DIR",
        help="the sequence, in order, with label-nyu40 ground truth (default: the demo's "
        "synthetic office rooms, made in OUT/scenes)",
    )
    e.add_argument("--out", type=Path, required=True, help="output folder (a rerun resumes)")
    e.add_argument(
        "--model",
        type=Path,
        default=None,
        metavar="CKPT",
        help="pre-trained checkpoint (default: pre-train the demo's light network on the "
        "pre-training scenes, once, into OUT/pretrained.safetensors)",
    )
    e.add_argument(
        "--pretrain-scenes",
        type=Path,
        nargs="+",
        default=[],
        metavar="SCENE_DIR",
        help="labelled pre-training scenes, replayed (default without SCENE_DIR: the demo's "
        "apartment rooms)",
    )
    e.add_argument("--preset", default="cpu", help="paper, cpu or tiny (default cpu)")
    e.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    e.add_argument(
        "--tables",
        default=",".join(TABLES),
        help=f"comma-separated parts of the report (default all: {','.join(TABLES)})",
    )
    e.add_argument(
        "--frameworks",
        default=",".join(FRAMEWORKS),
        help=f"NeRF presets of the frameworks table (default {','.join(FRAMEWORKS)})",
    )
    e.add_argument(
        "--redo",
        action="store_true",
        help="run every unit again (default: reuse the units an earlier invocation into "
        "--out finished with the same inputs)",
    )
    e.add_argument(
        "--size",
        type=size_arg,
        default=None,
        help="working size WxH (default: the network's; synthetic rooms are made at "
        f"{DEMO_SIZE[0]}x{DEMO_SIZE[1]} unless given)",
    )
    e.add_argument(
        "--device", default=None, help="cpu, cuda, cuda:1 ... (default: cuda if available)"
    )
    e.add_argument("--threads", type=positive_int, default=None, help="CPU threads for torch")
    synth = e.add_argument_group("synthetic rooms and pre-training (without SCENE_DIR / --model)")
    synth.add_argument("--frames", type=positive_int, default=60, help="frames per office room")
    synth.add_argument("--target-scenes", type=positive_int, default=3, help="office rooms")
    synth.add_argument("--pretrain-rooms", type=positive_int, default=16, help="apartment rooms")
    synth.add_argument(
        "--pretrain-frames", type=positive_int, default=30, help="frames per apartment room"
    )
    synth.add_argument("--pretrain-epochs", type=positive_int, default=20)
    synth.add_argument("--synth-seed", type=int, default=0, help="seed of rooms and pre-training")
    add_set_argument(e, "AdaptConfig of every run", "collapse.enabled=false")
    e.set_defaults(func=run_paper_command)


def _items(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def _rooms(folder: Path, family: str, count: int, frames: int, size, seed: int) -> list[Path]:
    """The demo's synthetic rooms in ``folder`` (made once: a rerun reads them back)."""
    from csa_core.data.synth import synthesize

    names = [folder / f"{family}_{seed}_{k}" for k in range(count)]
    if all(p.is_dir() for p in names):
        return names
    return synthesize(
        folder, scenes=count, frames=frames, size=size, family=family, seed=seed, overwrite=True
    )


def _pretrained(args: argparse.Namespace, paths: list[Path], size) -> Path:
    """``OUT/pretrained.safetensors``: the demo's light network pre-trained on ``paths``,
    made once per pre-training inputs (``pretrained.json`` records them) unless ``--redo``."""
    import json

    from csa_core.atomic_io import write_text_atomic
    from csa_core.cli.demo_adapt import pretrain_network
    from csa_core.data.scene_io import read_scene
    from csa_core.device import resolve_device

    ckpt, record = args.out / "pretrained.safetensors", args.out / "pretrained.json"
    wanted = {
        "scenes": [str(p) for p in paths],
        "size": list(size),
        "epochs": args.pretrain_epochs,
        "seed": args.synth_seed,
    }
    try:
        same = json.loads(record.read_text()) == wanted and ckpt.is_file()
    except (OSError, ValueError):
        same = False
    if same and not args.redo:
        print(f"reusing {ckpt} (pre-trained earlier on the same scenes)", file=sys.stderr)
        return ckpt
    scenes = [read_scene(p, size=size) for p in paths]
    device = str(resolve_device(args.device))
    print(f"pre-training the light network on {len(scenes)} scenes", file=sys.stderr)
    pretrain_network(scenes, size, args.pretrain_epochs, args.synth_seed, device, ckpt)
    write_text_atomic(record, json.dumps(wanted, indent=2) + "\n")
    return ckpt


def run_paper_command(args: argparse.Namespace) -> int:
    import torch

    from csa_core.errors import CSAInputError
    from csa_core.experiments.inputs import check_options, load_inputs, parse_seeds, versions
    from csa_core.experiments.paper import check_frameworks, check_tables, run
    from csa_core.experiments.report import write_report
    from csa_core.seg.config import paper_network_note

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    # Every option is checked before rooms are made or a network is pre-trained.
    seeds = parse_seeds(args.seeds)
    tables = check_tables(_items(args.tables))
    frameworks = check_frameworks(_items(args.frameworks))
    overrides = check_options(args.preset, overrides=args.set)
    scenes, pretrain = list(args.scenes), list(args.pretrain_scenes)
    synth_size = args.size or DEMO_SIZE
    if not scenes:
        root = args.out / "scenes"
        scenes = _rooms(
            root / "target",
            DEMO_TARGET_FAMILY,
            args.target_scenes,
            args.frames,
            synth_size,
            args.synth_seed + 1000,  # the demo's: other rooms than the pre-training ones
        )
        if not pretrain:
            pretrain = _rooms(
                root / "pretrain",
                DEMO_PRETRAIN_FAMILY,
                args.pretrain_rooms,
                args.pretrain_frames,
                synth_size,
                args.synth_seed,
            )
    model = args.model
    if model is None:
        if not pretrain:
            raise CSAInputError(
                "--model", "give a pre-trained checkpoint, or --pretrain-scenes to pre-train one"
            )
        model = _pretrained(args, pretrain, synth_size)
    inputs = load_inputs(
        model,
        scenes,
        args.out,
        preset_name=args.preset,
        seeds=seeds,
        pretrain_paths=pretrain,
        size=args.size,
        device=args.device,
        overrides=overrides,
        resume=not args.redo,
    )
    note = paper_network_note(args.preset, inputs.card.arch, inputs.size)
    if note:
        print(note, file=sys.stderr)
    report = run(inputs, tables, frameworks)
    described = {**inputs.describe(), "tables": tables, "frameworks": frameworks}
    written = write_report(report, args.out, described, versions())
    print(report.markdown)
    print()
    for path in written:
        print(f"wrote {path}")
    return 0


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
