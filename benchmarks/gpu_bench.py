"""The pipeline's speed on one accelerator, in one command and one table (not a test).

Run it first whenever a GPU is at hand; its table goes into ``benchmarks/results/gpu.md``
with the date and the GPU's name::

    python benchmarks/gpu_bench.py                    # every stage, about 5 minutes on one H200
    python benchmarks/gpu_bench.py --stages reference,render --profile
    python benchmarks/gpu_bench.py --smoke            # same stages at tiny sizes, CPU, < 1 minute

Stages (``--stages``, comma-separated; default all):

- ``reference``: training steps of the paper's preset (4096 rays, 256 + 256 samples) on a
  synthetic room at ``--size``: seconds per step, rays and samples per second, and the paper's
  5000-step budget extrapolated from the timed steps (``--reference-steps`` of them, after a
  warm-up fit that loads every kernel).
- ``fast``: the ``fast`` preset's whole fit (its steps and its semantic steps) of a
  ``--frames``-view room, as ``csa nerf fit`` runs it.
- ``render``: one image (colour and labels) of a novel view without depth, and the labels of
  a training view with its depth, for both presets, from the fitted models above; seconds per
  view over ``--render-views`` views rendered together, as ``render_frames`` batches them.
- ``map``: the voxel map of the Mapping baseline (``csa_core.adapt.baselines.voxel_map``) on
  the same room: build from the training frames, then the ray-cast read-back and the depth
  read-back, seconds per view.
- ``demo``: ``csa demo`` end to end in a child process, on the device.

Every timed region is synchronised with the device before its clock is read. Each stage
reports the device's peak memory (``torch.cuda.max_memory_allocated``; the process's peak
RSS on a CPU). ``--profile`` adds ``torch.profiler``'s table of the operators (CUDA kernels on
a GPU) with the most time over ``--profile-steps`` reference steps and one reference render,
and the number of kernel launches per step.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from csa_core.data.scene import Scene  # noqa: E402
from csa_core.data.synth import generate_scene, parse_size  # noqa: E402
from csa_core.device import resolve_device  # noqa: E402
from csa_core.eval.miou import ConfusionMatrix  # noqa: E402
from csa_core.nerf.config import NerfConfig, preset  # noqa: E402
from csa_core.nerf.fit import fit_semantic_nerf  # noqa: E402
from csa_core.nerf.model import SemanticNerf  # noqa: E402
from csa_core.nerf.render import render_frames  # noqa: E402
from csa_core.overrides import apply_overrides  # noqa: E402

STAGES = ("reference", "fast", "render", "map", "demo")
PAPER_STEPS = 5000  # the paper's NeRF budget (docs/method.md "Reference numbers")
LABELS = "label-nyu40"


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(device: torch.device, fn: Callable[[], Any]) -> tuple[float, Any]:
    """Seconds of ``fn()`` with the device synchronised before and after, and its result."""
    sync(device)
    t0 = time.perf_counter()
    result = fn()
    sync(device)
    return time.perf_counter() - t0, result


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def peak_mb(device: torch.device) -> float:
    """Peak device memory since the last reset (MB); on a CPU the process's peak RSS."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def config_of(name: str, sets: list[str]) -> NerfConfig:
    cfg = preset(name)
    return apply_overrides(cfg, sets) if sets else cfg


class Bench:
    """The stages, sharing one room and the models they fit."""

    def __init__(self, args: argparse.Namespace, device: torch.device, label: str = ""):
        self.args, self.device, self.label = args, device, label
        self.rows: list[dict[str, Any]] = []
        self.models: dict[str, SemanticNerf] = {}
        self._scene: Scene | None = None

    @property
    def scene(self) -> Scene:
        if self._scene is None:
            a = self.args
            t, self._scene = timed(
                torch.device("cpu"), lambda: generate_scene(a.family, a.seed, a.frames, a.size)
            )
            print(
                f"room {a.family}:{a.seed}, {a.frames} views at {a.size[0]}x{a.size[1]}: {t:.1f} s"
            )
        return self._scene

    def row(self, stage: str, what: str, value: float, unit: str, note: str = "") -> None:
        stage += self.label
        self.rows.append({"stage": stage, "what": what, "value": value, "unit": unit, "note": note})
        print(f"  {stage:9s} {what:46s} {value:10.4g} {unit:10s} {note}", flush=True)

    def fit(self, name: str, steps: int | None) -> tuple[SemanticNerf, Any]:
        cfg = config_of(name, self.args.set)
        return fit_semantic_nerf(
            self.scene, LABELS, cfg, device=self.device, steps=steps, progress=False
        )

    # -- stages -----------------------------------------------------------------------------

    def reference(self) -> None:
        a, dev = self.args, self.device
        self.fit("reference", a.warmup_steps)  # loads and compiles every kernel
        reset_peak(dev)
        seconds, (nerf, stats) = timed(dev, lambda: self.fit("reference", a.reference_steps))
        step_s = nerf.config.optim.rays_per_step / stats.rays_per_second
        self.models["reference"] = nerf
        self.row("reference", "training step", step_s, "s/step", f"{a.reference_steps} steps")
        self.row("reference", "rays per second", stats.rays_per_second, "rays/s")
        self.row("reference", "PSNR of the last step's rays", stats.final_psnr, "dB")
        self.row("reference", "samples per second", stats.samples_per_second, "samples/s")
        self.row(
            "reference",
            f"paper budget ({PAPER_STEPS} steps)",
            step_s * PAPER_STEPS,
            "s",
            "extrapolated",
        )
        self.row("reference", "peak memory", peak_mb(dev), "MB")

    def fast(self) -> None:
        a, dev = self.args, self.device
        self.fit("fast", a.warmup_steps)
        reset_peak(dev)
        seconds, (nerf, stats) = timed(dev, lambda: self.fit("fast", a.fast_steps))
        self.models["fast"] = nerf
        cfg = nerf.config
        note = f"{stats.steps} steps + semantic steps, {a.frames} views"
        self.row("fast", "whole fit", seconds, "s", note)
        self.row("fast", "training step", cfg.optim.rays_per_step / stats.rays_per_second, "s/step")
        self.row("fast", "samples per second", stats.samples_per_second, "samples/s")
        self.row("fast", "PSNR of the last step's rays", stats.final_psnr, "dB")
        self.row("fast", "peak memory", peak_mb(dev), "MB")

    def render(self) -> None:
        a, dev = self.args, self.device
        scene = self.scene
        frames = scene.train_frames[: a.render_views]
        poses = [(f.name, f.pose) for f in frames]
        depths = [f.depth for f in frames]
        for name in ("reference", "fast"):
            nerf = self.models.get(name)
            if nerf is None:
                nerf, _ = self.fit(name, a.warmup_steps)
                self.models[name] = nerf
            render_frames(nerf, poses[:1])  # warm-up
            render_frames(nerf, poses[:1], depths=depths[:1], color=False)
            reset_peak(dev)
            n = len(poses)
            t_novel, _ = timed(dev, lambda nerf=nerf: render_frames(nerf, poses))
            self.row("render", f"{name}: colour + labels, no depth", t_novel / n, "s/view")
            t_depth, views = timed(
                dev, lambda nerf=nerf: render_frames(nerf, poses, depths=depths, color=False)
            )
            self.row("render", f"{name}: labels of a view with depth", t_depth / n, "s/view")
            matrix = ConfusionMatrix()
            for f, v in zip(frames, views, strict=True):
                matrix.update(v.labels, f.labels[LABELS])
            self.row("render", f"{name}: mIoU of those labels", 100 * matrix.miou(), "%",
                     "fitted to the true labels")  # fmt: skip
            self.row("render", f"{name}: peak memory", peak_mb(dev), "MB")

    def map(self) -> None:
        from csa_core.adapt.baselines import voxel_map as vm

        a, dev = self.args, self.device
        scene = self.scene
        frames = scene.train_frames
        views = frames[: a.render_views]
        kwargs = (
            {"device": dev} if "device" in vm.VoxelSemanticMap.__init__.__code__.co_varnames else {}
        )
        where = "on the device" if kwargs else "numpy, CPU"
        reset_peak(dev)

        def build() -> Any:
            m = vm.VoxelSemanticMap(vm.VoxelMapConfig(), **kwargs)
            for f in frames:
                m.integrate(f.labels[LABELS], f.depth, f.pose, scene.intrinsics)
            return m

        build_s, m = timed(dev, build)
        self.row("map", f"build, {len(frames)} frames", build_s, "s", where)
        cast_s, _ = timed(dev, lambda: [m.labels_for_pose(f.pose, scene.intrinsics) for f in views])
        self.row("map", "ray-cast read-back", cast_s / len(views), "s/view", where)
        depth_s, _ = timed(
            dev, lambda: [m.labels_at_depth(f.depth, f.pose, scene.intrinsics) for f in views]
        )
        self.row("map", "depth read-back", depth_s / len(views), "s/view", where)
        self.row("map", "peak memory", peak_mb(dev), "MB")

    def demo(self) -> None:
        a = self.args
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [
                sys.executable,
                "-m",
                "csa_core.cli.main",
                "demo",
                "--out",
                f"{tmp}/demo",
                "--device",
                str(self.device),
                *a.demo_args,
            ]
            env = dict(os.environ, PYTHONPATH=str(REPO))
            t0 = time.perf_counter()
            done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
            seconds = time.perf_counter() - t0
            tail = (done.stdout + done.stderr).strip().splitlines()[-12:]
            print("\n".join("    | " + line for line in tail))
            if done.returncode != 0:
                self.row(
                    "demo", "csa demo end to end", float("nan"), "s", f"FAILED rc={done.returncode}"
                )
                return
            self.row("demo", "csa demo end to end", seconds, "s", " ".join(a.demo_args))

    # -- profile ----------------------------------------------------------------------------

    def profile(self) -> None:
        """torch.profiler over reference steps and one reference render."""
        from torch.profiler import ProfilerActivity, profile

        from csa_core.nerf.rays import RayBank
        from csa_core.nerf.trainer import NerfTrainer

        a, dev = self.args, self.device
        nerf = self.models.get("reference") or self.fit("reference", a.warmup_steps)[0]
        rays = RayBank(self.scene.train_frames, self.scene.intrinsics, dev, LABELS)
        trainer = NerfTrainer(nerf, rays, schedule_steps=1000)
        for _ in range(3):
            trainer.step()
        sync(dev)
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
        key = "cuda_time_total" if dev.type == "cuda" else "self_cpu_time_total"
        with profile(activities=acts) as prof:
            for _ in range(a.profile_steps):
                trainer.step()
            sync(dev)
        events = prof.key_averages()
        launches = sum(
            e.count for e in events if e.key.startswith(("cudaLaunchKernel", "cuLaunch"))
        )
        print(
            f"\nprofile: {a.profile_steps} reference steps; kernel launches per step: "
            f"{launches / a.profile_steps:.0f}"
        )
        print(events.table(sort_by=key, row_limit=a.profile_rows, max_name_column_width=60))
        f = self.scene.train_frames[0]
        with profile(activities=acts) as prof:
            render_frames(nerf, [(f.name, f.pose)])
            sync(dev)
        events = prof.key_averages()
        launches = sum(
            e.count for e in events if e.key.startswith(("cudaLaunchKernel", "cuLaunch"))
        )
        print(f"\nprofile: one reference render, colour + labels; kernel launches: {launches}")
        print(events.table(sort_by=key, row_limit=a.profile_rows, max_name_column_width=60))


def run_stages(bench: Bench, stages: list[str]) -> None:
    """Each stage in turn; one that fails is reported as a row and the others still run."""
    for stage in stages:
        try:
            getattr(bench, stage)()
        except Exception as e:  # noqa: BLE001 - a benchmark reports every stage it can
            traceback.print_exc()
            bench.row(stage, "FAILED", float("nan"), "", f"{type(e).__name__}: {e}"[:200])


def encoding_path(device: torch.device) -> str:
    """Which implementation encodes float32 positions on ``device`` (``auto``)."""
    from csa_core.nerf import hash_kernel, hash_triton

    x = torch.zeros(1, 3, device=device)
    if hash_kernel.usable(x, x):
        return "C kernel"
    if device.type == "cuda" and hash_triton.usable(x, torch.zeros(1, 2, device=device)):
        return "Triton kernel"
    return "PyTorch"


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| stage | what | value | unit | note |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['stage']} | {r['what']} | {r['value']:.4g} | {r['unit']} | {r['note']} |"
        )
    return "\n".join(lines)


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{platform.processor() or platform.machine()} CPU, {torch.get_num_threads()} threads"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--device", default="auto", help="torch device (default: CUDA when present)")
    p.add_argument(
        "--stages", default=",".join(STAGES), help=f"comma-separated, of {', '.join(STAGES)}"
    )
    p.add_argument(
        "--smoke", action="store_true", help="tiny sizes on the CPU: checks every stage runs"
    )
    p.add_argument("--family", default="office")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=250, help="views of the room")
    p.add_argument("--size", type=parse_size, default=(320, 240))
    p.add_argument("--reference-steps", type=int, default=300)
    p.add_argument("--fast-steps", type=int, default=None, help="default: the preset's")
    p.add_argument("--warmup-steps", type=int, default=20)
    p.add_argument("--render-views", type=int, default=8)
    p.add_argument("--demo-args", default="", help="extra arguments of csa demo (one string)")
    p.add_argument("--set", action="append", default=[], help="NeRF config override, KEY=VALUE")
    p.add_argument(
        "--compare", action="append", default=[],
        help="also run reference, fast and render with these overrides (KEY=VALUE,...)",
    )  # fmt: skip
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--profile", action="store_true")
    p.add_argument("--profile-steps", type=int, default=10)
    p.add_argument("--profile-rows", type=int, default=25)
    p.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = p.parse_args(argv)
    args.demo_args = args.demo_args.split()
    if args.smoke:
        args.device = "cpu" if args.device == "auto" else args.device
        args.frames, args.size = 6, (32, 24)
        args.reference_steps, args.fast_steps, args.warmup_steps = 2, 3, 1
        args.render_views, args.profile_steps = 2, 1
        args.set += [
            "optim.rays_per_step=256",
            "optim.semantic_steps=2",
            "optim.semantic_rays_per_step=256",
            "sampler.uniform_samples=16",
            "sampler.importance_samples=16",
        ]
        args.demo_args = (
            "--size 48x36 --frames 10 --pretrain-scenes 1 --pretrain-frames 10 "
            "--pretrain-epochs 1 --target-scenes 1 --preset tiny --seven-scenes absent"
        ).split() + args.demo_args
    stages = [s for s in args.stages.split(",") if s]
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        p.error(f"--stages: unknown {', '.join(unknown)} (choose from {', '.join(STAGES)})")
    args.stages = stages
    return args


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    print(
        f"device: {device_name(device)}; torch {torch.__version__}; "
        f"CPU threads {torch.get_num_threads()}",
        flush=True,
    )
    bench = Bench(args, device)
    run_stages(bench, args.stages)
    print(f"hash encoding on {device.type}: {encoding_path(device)}")
    for extra in args.compare:
        # The same room and stages with more overrides, side by side in this process.
        variant = argparse.Namespace(**{**vars(args), "set": args.set + extra.split(",")})
        other = Bench(variant, device, label=f" [{extra}]")
        other._scene = bench._scene
        run_stages(other, [s for s in args.stages if s in ("reference", "fast", "render")])
        bench.rows += other.rows
    if args.profile:
        bench.profile()
    print(
        f"\n{device_name(device)}, {time.strftime('%Y-%m-%d')}, "
        f"room {args.family}:{args.seed} {args.frames} views at {args.size[0]}x{args.size[1]}"
    )
    print(table(bench.rows))
    if args.json is not None:
        args.json.write_text(json.dumps(bench.rows, indent=1))
    return bench.rows


if __name__ == "__main__":
    main()
