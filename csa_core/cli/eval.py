"""``csa eval``: score label maps against ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="score label maps (mIoU, pixel and class accuracy)")
    cmds = p.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)
    m = cmds.add_parser(
        "miou", help="mIoU of a folder of predicted label maps against a ground-truth folder"
    )
    m.add_argument("pred_dir", type=Path, help="predicted labels, <frame>.png uint8 NYU40 ids")
    m.add_argument("gt_dir", type=Path, help="ground truth, same file names (0 = ignored)")
    m.add_argument(
        "--predicted-only",
        action="store_true",
        help="score the frames pred_dir has (each needs a ground truth), not every "
        "ground-truth frame: e.g. a render of the training views against the scene's labels",
    )
    m.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    m.set_defaults(func=_miou)


def _miou(args: argparse.Namespace) -> int:
    from csa_core.atomic_io import write_text_atomic
    from csa_core.eval.miou import evaluate_label_folders, format_miou_table

    summary = evaluate_label_folders(args.pred_dir, args.gt_dir, args.predicted_only)
    print(format_miou_table(summary, title=f"{args.pred_dir} vs {args.gt_dir}"))
    if args.json is not None:
        write_text_atomic(args.json, json.dumps(summary, indent=2, default=float))
    return 0
