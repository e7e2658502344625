"""``csa nerf``: fit a Semantic-NeRF to a scene folder, render it, inspect a checkpoint."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from csa_core.cli.args import add_set_argument, positive_int, size_arg

if TYPE_CHECKING:
    from csa_core.nerf.config import NerfConfig


def add_nerf_commands(sub: argparse._SubParsersAction) -> None:
    """Add the ``nerf`` command group (fit, render, info) to the ``csa`` parser."""
    from csa_core.nerf.config import PRESETS

    p = sub.add_parser("nerf", help="fit, render and inspect scene NeRFs (the 3D label fusion)")
    cmds = p.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)

    f = cmds.add_parser("fit", help="fit a Semantic-NeRF to a scene's frames and one label folder")
    f.add_argument(
        "scene", type=Path, help="scene folder (color/, depth/, pose/, intrinsic/, label folders)"
    )
    f.add_argument(
        "--labels",
        default="label-nyu40",
        help=(
            "label folder to fuse (e.g. label-nyu40 or predictions); 'none' for colour and depth "
            "only"
        ),
    )
    f.add_argument(
        "--out", type=Path, required=True, help="checkpoint file to write (.safetensors)"
    )
    f.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="fast",
        help="reference = paper values; fast = CPU-friendly (default)",
    )
    f.add_argument(
        "--steps", type=positive_int, default=None, help="override the preset's step count"
    )
    f.add_argument(
        "--size",
        type=size_arg,
        default=None,
        help="working size WxH (default: the scene's colour size)",
    )
    f.add_argument("--every", type=positive_int, default=1, help="keep every N-th frame")
    f.add_argument(
        "--dtype",
        choices=("float16", "float32"),
        default=None,
        help="checkpoint storage (default: the preset's)",
    )
    f.add_argument(
        "--device", default="auto", help="auto (CUDA if available), cpu, cuda, cuda:1, ..."
    )
    f.add_argument("--seed", type=int, default=None)
    f.add_argument("--overwrite", action="store_true")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    add_set_argument(f, "NerfConfig", "loss.free_space=0 or sampler.train=reference")
    f.set_defaults(func=_fit)

    r = cmds.add_parser("render", help="render colour, depth and NYU40 labels from a checkpoint")
    r.add_argument("checkpoint", type=Path)
    r.add_argument(
        "--scene", type=Path, default=None, help="scene folder (needed for --views val/all)"
    )
    r.add_argument("--views", choices=("train", "val", "all", "novel"), default="train")
    r.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output folder (a scene folder with label-nyu40/ and preview/)",
    )
    r.add_argument(
        "--every",
        type=positive_int,
        default=1,
        help="with --scene: keep every N-th frame (as when fitting)",
    )
    r.add_argument(
        "--sampler",
        choices=("reference", "occupancy"),
        default=None,
        help="default: the checkpoint's render sampler",
    )
    r.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change a render option of the checkpoint's config for this render only "
        f"({', '.join(RENDER_KEYS)}*), e.g. sampler.render_novel_estimate=true; repeatable",
    )
    r.add_argument("--no-previews", action="store_true")
    r.add_argument("--device", default="auto")
    r.add_argument("--overwrite", action="store_true")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=_render)

    i = cmds.add_parser("info", help="print a checkpoint's metadata as JSON")
    i.add_argument("checkpoint", type=Path)
    i.set_defaults(func=_info)


register = add_nerf_commands


def fit_config(args: argparse.Namespace) -> NerfConfig:
    """The fit's config: the preset, then ``--steps`` (the semantic steps after the fit scale
    with it: ``scaled_semantic_steps``), ``--dtype`` and ``--seed``, then the ``--set``
    overrides (the last word), all as items of ``build_config``. The checkpoint stores it."""
    from csa_core.nerf.config import build_config, preset, scaled_semantic_steps

    flags = []
    if args.steps is not None:
        semantic = scaled_semantic_steps(preset(args.preset).optim, args.steps)
        flags += [f"optim.semantic_steps={semantic}", f"optim.steps={args.steps}"]
    if args.dtype is not None:
        flags.append(f"storage_dtype={args.dtype}")
    if args.seed is not None:
        flags.append(f"seed={args.seed}")
    return build_config(args.preset, [*flags, *args.set])


def _fit(args: argparse.Namespace) -> int:
    from csa_core.data.scene_io import read_scene
    from csa_core.errors import CSAInputError
    from csa_core.nerf.checkpoint import save_checkpoint
    from csa_core.nerf.fit import fit_semantic_nerf

    if args.out.exists() and not args.overwrite:
        raise CSAInputError(args.out, "output already exists (pass --overwrite to replace it)")
    if args.out.is_dir():
        raise CSAInputError(args.out, "is a folder: --out names the checkpoint file to write")
    cfg = fit_config(args)
    labels = None if args.labels.lower() == "none" else args.labels
    scene = read_scene(
        args.scene, size=args.size, labels=[labels] if labels else [], every=args.every
    )
    nerf, stats = fit_semantic_nerf(scene, labels, cfg, device=args.device, progress=not args.quiet)
    size = save_checkpoint(nerf, args.out)
    print(
        f"{args.out}: {size / 1e6:.2f} MB, {stats.steps} steps in {stats.seconds:.1f} s "
        f"({stats.rays_per_second:,.0f} rays/s), train PSNR {stats.final_psnr:.2f} dB"
    )
    return 0


# Keys (prefixes) of a NeRF config that only decide how a fitted model renders: the one
# override path (csa_core.overrides) may change them on a loaded checkpoint; everything else
# describes the fitted weights and is set at ``csa nerf fit``.
RENDER_KEYS = (
    "sampler.render",
    "sampler.max_render_samples",
    "render_unseen_unknown",
    "render_chunk",
)


def _render(args: argparse.Namespace) -> int:
    from csa_core.data.scene_io import read_scene
    from csa_core.errors import CSAInputError
    from csa_core.nerf.checkpoint import load_checkpoint
    from csa_core.nerf.render import check_scene_matches, render_views, write_rendered_views
    from csa_core.overrides import apply_overrides

    for item in args.set:
        key = item.partition("=")[0].strip()
        if not key.startswith(RENDER_KEYS):
            raise CSAInputError(
                f"--set {item}",
                f"{key or 'KEY'} is not a render option: csa nerf render changes only "
                f"{', '.join(k + '*' for k in RENDER_KEYS)}; the rest belongs to the fitted "
                "model (csa nerf fit --set)",
            )
    if args.out.exists() and not args.overwrite:  # before the renders, not after them
        raise CSAInputError(args.out, "output already exists (pass --overwrite to replace it)")
    nerf = load_checkpoint(args.checkpoint, device=args.device)
    apply_overrides(nerf.config, args.set)
    scene = None
    if args.scene is not None:
        intr = nerf.info.intrinsics
        scene = read_scene(args.scene, size=(intr.width, intr.height), labels=[], every=args.every)
        check_scene_matches(nerf, scene, args.scene)
    elif args.views in ("val", "all"):
        raise CSAInputError("--scene", f"--views {args.views} needs the scene folder")
    views = render_views(nerf, scene, args.views, sampler=args.sampler, progress=not args.quiet)
    intr = scene.intrinsics if scene is not None else nerf.info.intrinsics
    write_rendered_views(
        views, args.out, intr, overwrite=args.overwrite, previews=not args.no_previews
    )
    print(f"{args.out}: {len(views)} {args.views} views")
    return 0


def _info(args: argparse.Namespace) -> int:
    from csa_core.nerf.checkpoint import checkpoint_info

    print(json.dumps(checkpoint_info(args.checkpoint), indent=2))
    return 0
