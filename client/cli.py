"""``csa-client``: the CSA service from the command line.

The server URL and API key come from ``--url`` / ``--api-key`` or the environment
(``CSA_URL``, ``CSA_API_KEY``). Errors print one line and exit 1 (2 for bad arguments).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from client.csa_client import CSAClient
from client.errors import CSAError
from client.models import Job, MemoryBank

console = Console()
err_console = Console(stderr=True)


def _fail(message: str) -> None:
    """One unwrapped line on stderr."""
    print(f"csa-client: {message}", file=sys.stderr)


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def _read_matrix(path: Path, shapes: tuple[tuple[int, int], ...]) -> list[list[float]]:
    try:
        rows = [
            [float(x) for x in line.split()]
            for line in path.read_text().splitlines()
            if line.strip()
        ]
    except (OSError, ValueError) as e:
        raise CSAError(f"{path}: not a numeric matrix ({e})") from None
    shape = (len(rows), len(rows[0]) if rows else 0)
    if shape not in shapes or any(len(r) != shape[1] for r in rows):
        raise CSAError(
            f"{path}: expected a {' or '.join(f'{a}x{b}' for a, b in shapes)} matrix, got "
            f"{shape[0]}x{shape[1]}"
        )
    return rows


def _job_table(jobs: list[Job]) -> Table:
    t = Table()
    for col in ("id", "kind", "status", "progress", "message", "created"):
        t.add_column(col, max_width=70 if col == "message" else None, overflow="fold")
    for j in jobs:
        t.add_row(
            str(j.id),
            j.kind,
            j.status,
            f"{100 * j.progress:.0f}%",
            j.error or j.message,
            j.created_at.isoformat(timespec="seconds"),
        )
    return t


def _wait(client: CSAClient, job: Job, timeout: float | None) -> Job:
    """Follow a job with a progress bar until it ends."""
    with Progress(
        TextColumn("[bold]job {task.fields[job]}[/] {task.fields[kind]}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[msg]}"),
        console=err_console,
    ) as bar:
        task = bar.add_task("job", total=1.0, job=job.id, kind=job.kind, msg=job.message)

        def update(j: Job) -> None:
            bar.update(task, completed=j.progress, msg=(j.error or j.message)[:60])

        final = client.wait_job(job.id, timeout=timeout, on_progress=update, raise_on_failure=False)
    return final


def cmd_health(client: CSAClient, args: argparse.Namespace) -> int:
    h = client.health()
    if args.json:
        console.print_json(h.model_dump_json())
        return 0 if h.status == "ok" else 1
    console.print(
        f"status: {h.status}  version {h.version}  database {h.database}  workers alive "
        f"{h.workers_alive}",
        markup=False,
        highlight=False,
    )
    console.print("capabilities:", markup=False, highlight=False)
    for name, reason in sorted(h.capabilities.items()):
        # The server reports null for an available capability, else why it is not.
        console.print(
            f"  {name}: {'available' if reason is None else f'not available ({reason})'}",
            markup=False,
            highlight=False,
        )
    return 0 if h.status == "ok" else 1


def cmd_upload(client: CSAClient, args: argparse.Namespace) -> int:
    scene, result = client.upload_scene_folder(
        args.scene_dir, scene=args.name, replace=args.replace
    )
    console.print(
        f"scene {scene.name} (id {scene.id}): {len(result.added)} added, "
        f"{len(result.unchanged)} unchanged, {len(result.replaced)} replaced, "
        f"{len(result.skipped)} skipped; {scene.num_frames} frames stored"
    )
    for s in result.skipped:
        console.print(f"  skipped {s.name}: {s.reason}")
    return 0


def _submit(client: CSAClient, job: Job, args: argparse.Namespace) -> int:
    console.print(f"job {job.id} ({job.kind}) {job.status}")
    if not args.wait:
        return 0
    final = _wait(client, job, args.timeout_wait)
    if final.status != "succeeded":
        _fail(f"job {final.id} {final.status}: {final.error or final.message}")
        return 1
    console.print_json(json.dumps(final.result or {}))
    return 0


def cmd_adapt(client: CSAClient, args: argparse.Namespace) -> int:
    return _submit(
        client, client.adapt(args.scene, model=args.model, preset=args.preset, mode=args.mode), args
    )


def cmd_fit_nerf(client: CSAClient, args: argparse.Namespace) -> int:
    return _submit(
        client,
        client.fit_nerf(
            args.scene, labels=args.labels, preset=args.preset, steps=args.steps, model=args.model
        ),
        args,
    )


def cmd_evaluate(client: CSAClient, args: argparse.Namespace) -> int:
    return _submit(
        client, client.evaluate(model=args.model, scenes=args.scene or None, split=args.split), args
    )


def cmd_pretrain(client: CSAClient, args: argparse.Namespace) -> int:
    job = client.pretrain(args.scene, epochs=args.epochs, arch=args.arch, name=args.name)
    return _submit(client, job, args)


def cmd_jobs(client: CSAClient, args: argparse.Namespace) -> int:
    if args.job_id is None:
        console.print(_job_table(client.jobs(status=args.status, limit=args.limit)))
        return 0
    if args.cancel:
        job = client.cancel_job(args.job_id)
        console.print(f"job {job.id}: {job.status} ({job.message})")
        return 0
    if args.wait:
        job = _wait(client, client.job(args.job_id), args.timeout_wait)
        console.print(f"job {job.id}: {job.status} {job.error or ''}")
        return 0 if job.status == "succeeded" else 1
    if args.log:
        for line in client.job_log(args.job_id, tail=args.tail):
            console.print(
                f"{line.time.isoformat(timespec='seconds')} {line.level:7s} {line.message}",
                markup=False,
                highlight=False,
            )
        return 0
    console.print_json(client.job(args.job_id).model_dump_json())
    return 0


def cmd_models(client: CSAClient, args: argparse.Namespace) -> int:
    if args.ref is None:
        t = Table()
        for col in (
            "id",
            "name",
            "lineage",
            "parent",
            "adapted to",
            "arch",
            "MB",
            "val mIoU",
            "current",
        ):
            t.add_column(col)
        for m in client.models(lineage=args.lineage):
            t.add_row(
                str(m.id),
                m.name,
                m.lineage,
                str(m.parent_id or "-"),
                m.adapted_scene or "-",
                m.arch,
                f"{m.size_bytes / 1e6:.1f}",
                _pct(m.metrics.get("val_miou")),
                "*" if m.is_current else "",
            )
        console.print(t)
        return 0
    if args.set_current:
        m = client.set_current_model(args.ref)
        console.print(f"current model: {m.name} (id {m.id})")
    if args.download is not None:
        path = client.download_model(args.ref, args.download)
        console.print(f"saved {path}")
    if not args.set_current and args.download is None:
        console.print_json(client.model(args.ref).model_dump_json())
    return 0


def cmd_register(client: CSAClient, args: argparse.Namespace) -> int:
    m = client.register_model(
        args.checkpoint,
        name=args.name,
        lineage=args.lineage,
        make_current=True if args.current else None,
    )
    console.print(
        f"registered {m.name} (id {m.id}, lineage "
        f"{m.lineage}){' as current' if m.is_current else ''}"
    )
    return 0


def cmd_metrics(client: CSAClient, args: argparse.Namespace) -> int:
    m = client.continual_metrics(lineage=args.lineage, split=args.split)
    t = Table(title=f"lineage {m.lineage}: mIoU (%) on each scene's {m.split} views")
    t.add_column("after step")
    for s in m.steps:
        t.add_column(s.scene or str(s.scene_id))
    t.add_row("pre-trained", *[_pct(v) for v in m.b])
    for s, row in zip(m.steps, m.R, strict=True):
        t.add_row(f"{s.step}: {s.model}", *[_pct(v) for v in row])
    console.print(t)
    console.print(f"ACC {_pct(m.acc)}  A {_pct(m.a)}  FWT {_pct(m.fwt)}  BWT {_pct(m.bwt)}")
    if m.missing:
        console.print(f"missing entries (run evaluate jobs): {', '.join(m.missing)}")
    return 0


def _quality_value(key: str, value: object) -> str:
    """One number of a NeRF's quality, in the unit its name says (``*_psnr`` dB, ``*_m``
    metres, ``*_seconds``, ``*miou*`` as a percentage)."""
    if value is None:
        return "-"
    if isinstance(value, bool) or not isinstance(value, int | float):
        return str(value)
    if key.endswith("_psnr"):
        return f"{value:.1f} dB"
    if key.endswith("_m"):
        return f"{value:.3f} m"
    if key.endswith("_seconds"):
        return f"{value:.1f} s"
    if "miou" in key:
        return f"{100 * value:.1f}%"
    return str(value) if isinstance(value, int) else f"{value:.4g}"


def quality_lines(quality: dict[str, object], skip: tuple[str, ...] = ("preset",)) -> list[str]:
    """A NeRF's quality numbers as ``name value`` lines (``val_depth_mae_m`` -> ``val depth mae
    0.051 m``), in the server's order; ``skip`` names keys shown elsewhere."""
    lines = []
    for key, value in quality.items():
        if key in skip:
            continue
        name = key.removesuffix("_seconds").removesuffix("_m").replace("_", " ")
        lines.append(f"{name} {_quality_value(key, value)}")
    return lines


def memory_table(bank: MemoryBank) -> Table:
    t = Table(title=f"memory bank: {bank.num_scenes} scenes, {bank.total_bytes / 1e6:.2f} MB")
    for col in ("scene", "nerf", "MB", "preset", "labels", "quality"):
        t.add_column(col, overflow="fold")
    for e in bank.entries:
        t.add_row(
            e.scene,
            str(e.id),
            f"{e.size_bytes / 1e6:.2f}",
            e.preset,
            e.labels_source,
            "\n".join(quality_lines(e.quality)) or "-",
        )
    return t


def cmd_memory(client: CSAClient, args: argparse.Namespace) -> int:
    console.print(memory_table(client.memory()))
    return 0


def _write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_bytes(data)
    tmp.replace(path)


def cmd_predict(client: CSAClient, args: argparse.Namespace) -> int:
    pred = client.predict(args.image, model=args.model, format="color" if args.color else "ids")
    _write(args.out, pred.png)
    console.print(f"{args.out}: labels from {pred.model} (id {pred.model_id})")
    return 0


def cmd_render(client: CSAClient, args: argparse.Namespace) -> int:
    pose = _read_matrix(args.pose, ((4, 4),))
    intrinsics = None
    if args.intrinsics is not None:
        if args.size is None:
            raise CSAError("--intrinsics needs --size WxH")
        K = _read_matrix(args.intrinsics, ((3, 3), (4, 4)))
        intrinsics = {
            "fx": K[0][0],
            "fy": K[1][1],
            "cx": K[0][2],
            "cy": K[1][2],
            "width": args.size[0],
            "height": args.size[1],
        }
    view = client.render(args.scene, pose, intrinsics=intrinsics, channels=args.channels)
    for name, png in view.images.items():
        _write(args.out / f"{name}.png", png)
    console.print(
        f"{args.out}: {', '.join(f'{n}.png' for n in view.images)} ({view.width}x{view.height}, "
        f"NeRF {view.nerf_id})"
    )
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from None
    return w, h


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="csa-client",
        description=(
            "Talk to a CSA server (URL and key from --url/--api-key or CSA_URL/CSA_API_KEY)."
        ),
    )
    p.add_argument(
        "--url", default=None, help="server URL (default: $CSA_URL or http://127.0.0.1:8000)"
    )
    p.add_argument("--api-key", default=None, help="API key (default: $CSA_API_KEY)")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds per request (default 30)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    s = sub.add_parser("health", help="server status and capabilities")
    s.add_argument("--json", action="store_true", help="print the server's answer as JSON")
    s.set_defaults(func=cmd_health)

    s = sub.add_parser(
        "upload", help="upload a scene folder (creates the scene; re-uploading is harmless)"
    )
    s.add_argument("scene_dir", type=Path)
    s.add_argument("--name", default=None, help="scene name (default: the folder name)")
    s.add_argument("--replace", action="store_true", help="overwrite stored frames that differ")
    s.set_defaults(func=cmd_upload)

    def waitable(sp: argparse.ArgumentParser) -> None:
        sp.add_argument(
            "--wait", action="store_true", help="follow the job with a progress bar until it ends"
        )
        sp.add_argument(
            "--timeout-wait",
            type=float,
            default=None,
            help="give up waiting after this many seconds",
        )

    s = sub.add_parser("adapt", help="adapt the model to a scene (a continual step)")
    s.add_argument("--scene", required=True, help="scene name or id")
    s.add_argument("--model", default=None, help="selects the lineage (default: current model's)")
    s.add_argument(
        "--preset", default="cpu", help="adaptation preset: paper, cpu or tiny (default cpu)"
    )
    s.add_argument(
        "--mode",
        default=None,
        choices=("joint", "ni_nl", "gi_nl"),
        help="default: the preset's (joint)",
    )
    waitable(s)
    s.set_defaults(func=cmd_adapt)

    s = sub.add_parser("fit-nerf", help="fit a scene's Semantic-NeRF (memory bank)")
    s.add_argument("--scene", required=True)
    s.add_argument(
        "--labels", default="predictions", choices=("predictions", "ground_truth", "none")
    )
    s.add_argument("--model", default=None)
    s.add_argument("--preset", default="fast", choices=("fast", "reference"))
    s.add_argument("--steps", type=int, default=None)
    waitable(s)
    s.set_defaults(func=cmd_fit_nerf)

    s = sub.add_parser("evaluate", help="score a model on labelled scenes")
    s.add_argument("--model", default=None)
    s.add_argument(
        "--scene", action="append", help="scene (repeatable; default: all labelled scenes)"
    )
    s.add_argument("--split", default="val", choices=("val", "train", "all"))
    waitable(s)
    s.set_defaults(func=cmd_evaluate)

    s = sub.add_parser("pretrain", help="train a new network on labelled scenes")
    s.add_argument("--scene", action="append", required=True, help="scene (repeatable)")
    s.add_argument("--epochs", type=int, default=12)
    s.add_argument("--arch", default=None)
    s.add_argument("--name", default=None)
    waitable(s)
    s.set_defaults(func=cmd_pretrain)

    s = sub.add_parser("jobs", help="list jobs, or show / follow / cancel one")
    s.add_argument("job_id", type=int, nargs="?")
    s.add_argument(
        "--status", default=None, choices=("queued", "running", "succeeded", "failed", "cancelled")
    )
    s.add_argument("--limit", type=int, default=30)
    s.add_argument("--log", action="store_true", help="print the job's log")
    s.add_argument("--tail", type=int, default=50)
    s.add_argument("--cancel", action="store_true")
    waitable(s)
    s.set_defaults(func=cmd_jobs)

    s = sub.add_parser("models", help="list model versions, or show / set current / download one")
    s.add_argument("ref", nargs="?", help="id, name or 'current'")
    s.add_argument("--lineage", default=None)
    s.add_argument("--set-current", action="store_true")
    s.add_argument("--download", type=Path, default=None, metavar="PATH")
    s.set_defaults(func=cmd_models)

    s = sub.add_parser("register-model", help="register a segmentation checkpoint file")
    s.add_argument("checkpoint", type=Path)
    s.add_argument("--name", required=True)
    s.add_argument("--lineage", default=None)
    s.add_argument("--current", action="store_true", help="make it the current model")
    s.set_defaults(func=cmd_register)

    s = sub.add_parser("metrics", help="R matrix and continual scores (ACC, A, FWT, BWT)")
    s.add_argument("--lineage", default=None)
    s.add_argument("--split", default="val", choices=("val", "train", "all"))
    s.set_defaults(func=cmd_metrics)

    sub.add_parser("memory", help="the NeRF memory bank").set_defaults(func=cmd_memory)

    s = sub.add_parser("predict", help="label an image (PNG of NYU40 ids)")
    s.add_argument("image", type=Path)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--model", default=None, help="model id or name (default: current)")
    s.add_argument("--color", action="store_true", help="write the palette picture instead of ids")
    s.set_defaults(func=cmd_predict)

    s = sub.add_parser("render", help="render colour, depth and labels from a scene's NeRF")
    s.add_argument("--scene", required=True)
    s.add_argument("--pose", type=Path, required=True, help="4x4 camera-to-world matrix file")
    s.add_argument(
        "--out", type=Path, default=Path("render"), help="output folder (default: render/)"
    )
    s.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="3x3/4x4 intrinsics (default: the scene's camera)",
    )
    s.add_argument("--size", type=_size, default=None, help="WxH for --intrinsics")
    s.add_argument(
        "--channels",
        nargs="+",
        default=["color", "depth", "labels"],
        choices=("color", "depth", "labels", "labels_color"),
    )
    s.set_defaults(func=cmd_render)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with CSAClient(args.url, args.api_key, timeout=args.timeout) as client:
            return int(args.func(client, args) or 0)
    except CSAError as e:
        _fail(f"error: {e}")
        return 1
    except OSError as e:
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        _fail(f"error: {where}{e.strerror or e}")
        return 1
    except KeyboardInterrupt:
        _fail("interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
