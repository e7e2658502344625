"""``csa data``: make, import, inspect and preview scene folders."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from csa_core.cli.args import positive_int, size_arg

# The importer's ``csa_core.data.sevenscenes.CAMERAS``, spelt out here so that building the
# parser does not import OpenCV; a test keeps the two equal.
CAMERA_CHOICES = ("color", "depth")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("data", help="make, import, inspect and preview scene folders")
    cmds = p.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)

    s = cmds.add_parser(
        "synth", help="render procedural rooms with NYU40 labels (the embedded default data)"
    )
    s.add_argument("out", type=Path, help="folder that receives one scene folder per room")
    s.add_argument("--scenes", type=positive_int, default=1)
    s.add_argument("--frames", type=positive_int, default=60)
    s.add_argument("--size", type=size_arg, default=(160, 120), help="WxH (default 160x120)")
    s.add_argument("--family", default="apartment", help="room family (see `csa data families`)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument(
        "--capture",
        default="walk",
        help="walk: a smooth hand-held walk (default); random: viewpoints spread at random "
        "through the room's free space, each looking at a random target",
    )
    s.add_argument("--overwrite", action="store_true")
    s.set_defaults(func=_synth)

    g = cmds.add_parser(
        "degrade",
        help="make a Kinect-like capture of a clean scene: noisy depth with holes, noisy colour, "
        "labels with systematic and per-frame errors",
    )
    g.add_argument("src", type=Path, help="clean scene folder (exact depth and labels)")
    g.add_argument("dst", type=Path, help="scene folder to write")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument(
        "--source", default="label-nyu40", help="label folder the noisy labels start from"
    )
    g.add_argument(
        "--target", default="label-noisy", help="label folder that receives the noisy labels"
    )
    g.add_argument("--no-labels", action="store_true", help="degrade colour and depth only")
    g.add_argument("--overwrite", action="store_true")
    g.set_defaults(func=_degrade)

    f = cmds.add_parser("families", help="list the synthetic room families")
    f.set_defaults(func=_families)

    i = cmds.add_parser("import-7scenes", help="convert a 7-Scenes sequence into a scene folder")
    i.add_argument("src", type=Path)
    i.add_argument("out", type=Path)
    i.add_argument("--every", type=positive_int, default=1, help="keep every N-th frame")
    i.add_argument(
        "--size", type=size_arg, default=None, help="working size WxH (default: source size)"
    )
    i.add_argument("--overwrite", action="store_true")
    i.add_argument(
        "--camera",
        choices=CAMERA_CHOICES,
        default="color",
        help=(
            "color: move frames to the Kinect colour camera (default); depth: the raw depth-camera "
            "frames"
        ),
    )
    i.set_defaults(func=_import_7scenes)

    n = cmds.add_parser("info", help="summarise a scene folder")
    n.add_argument("scene", type=Path)
    n.add_argument(
        "--labels", default="all", help="label folder(s) to read, comma-separated, or 'all'"
    )
    n.add_argument(
        "--label-map", type=Path, default=None, help="scannetv2-labels.combined.tsv for label-filt"
    )
    n.set_defaults(func=_info)

    v = cmds.add_parser(
        "preview", help="write colourised labels and overlays for people to look at"
    )
    v.add_argument("scene", type=Path)
    v.add_argument("--out", type=Path, required=True)
    v.add_argument("--labels", default="label-nyu40", help="label folder to show")
    v.add_argument("--label-map", type=Path, default=None)
    v.add_argument("--every", type=positive_int, default=1)
    v.add_argument("--overwrite", action="store_true")
    v.set_defaults(func=_preview)


def _label_spec(text: str) -> str | list[str]:
    return "all" if text == "all" else [t for t in text.split(",") if t]


def _synth(args: argparse.Namespace) -> int:
    from csa_core.data.synth import synthesize

    paths = synthesize(
        args.out,
        scenes=args.scenes,
        frames=args.frames,
        size=args.size,
        family=args.family,
        seed=args.seed,
        overwrite=args.overwrite,
        capture=args.capture,
    )
    for p in paths:
        print(p)
    return 0


def _degrade(args: argparse.Namespace) -> int:
    from csa_core.data.synth import degrade_scene_folder

    source = None if args.no_labels else args.source
    scene = degrade_scene_folder(
        args.src, args.dst, args.seed, source=source, target=args.target, overwrite=args.overwrite
    )
    measured = np.mean([float((f.depth > 0).mean()) for f in scene.frames])
    line = f"{args.dst}: {len(scene)} frames, {100 * measured:.1f}% of pixels with depth"
    if source is not None:
        hits = sum(int((f.labels[args.target] == f.labels[source]).sum()) for f in scene.frames)
        total = sum(f.labels[source].size for f in scene.frames)
        line += f", {args.target} agrees with {source} on {100 * hits / total:.1f}% of pixels"
    print(line)
    return 0


def _families(args: argparse.Namespace) -> int:
    from csa_core.data.synth import FAMILIES

    for name, fam in FAMILIES.items():
        doc = (getattr(fam, "description", "") or "").strip()
        print(f"{name:12s} {doc}")
    return 0


def _import_7scenes(args: argparse.Namespace) -> int:
    from csa_core.data.sevenscenes import import_7scenes

    scene = import_7scenes(
        args.src,
        args.out,
        every=args.every,
        size=args.size,
        overwrite=args.overwrite,
        camera=args.camera,
    )
    w, h = scene.size
    print(f"{args.out}: {len(scene)} frames at {w}x{h} ({len(scene.skipped)} skipped)")
    return 0


def _info(args: argparse.Namespace) -> int:
    from csa_core.data.nyu40 import CLASS_NAMES
    from csa_core.data.scene_io import read_scene

    scene = read_scene(args.scene, labels=_label_spec(args.labels), label_map=args.label_map)
    k = scene.intrinsics
    print(f"scene       {scene.name}")
    print(
        f"frames      {len(scene)} ({scene.num_train} train / {len(scene.val_frames)} val), "
        f"{len(scene.skipped)} skipped"
    )
    print(
        f"size        {k.width}x{k.height}  fx={k.fx:.2f} fy={k.fy:.2f} cx={k.cx:.2f} cy={k.cy:.2f}"
    )
    depths = [f.depth for f in scene.frames if f.depth is not None]
    if depths:
        d = np.stack(depths)
        valid = d > 0
        print(
            f"depth       {valid.mean() * 100:.1f}% measured, "
            f"{d[valid].min():.3f}..{d[valid].max():.3f} m"
        )
    else:
        print("depth       none")
    centres = np.stack([f.pose[:3, 3] for f in scene.frames])
    path_len = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    print(f"trajectory  {path_len:.2f} m")
    for folder in scene.label_folders:
        labs = np.stack([f.labels[folder] for f in scene.frames if folder in f.labels])
        counts = np.bincount(labs.ravel(), minlength=41)
        top = [i for i in np.argsort(-counts) if i > 0 and counts[i] > 0]
        names = ", ".join(f"{CLASS_NAMES[i]} {counts[i] / labs.size * 100:.0f}%" for i in top[:8])
        print(
            f"{folder:11s} {len(top)} classes, {counts[0] / labs.size * 100:.1f}% unknown; {names}"
        )
    for s in scene.skipped:
        print(f"skipped     {s.name}: {s.reason}")
    return 0


def _preview(args: argparse.Namespace) -> int:
    from csa_core.atomic_io import atomic_dir
    from csa_core.data.label_images import save_preview
    from csa_core.data.scene_io import read_scene

    scene = read_scene(args.scene, labels=[args.labels], label_map=args.label_map, every=args.every)
    with atomic_dir(args.out, overwrite=args.overwrite) as tmp:
        for f in scene.frames:
            save_preview(tmp / f"{f.name}.png", f.color, f.labels[args.labels])
    print(f"{args.out}: {len(scene)} previews")
    return 0
