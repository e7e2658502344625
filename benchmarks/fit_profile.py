"""Where a label-fusion fit and its renders spend their time, phase by phase (not a test).

Fits one NeRF preset to a synthetic room's per-frame corrupted labels (as the fusion
benchmark's ``--noise`` does), renders the training views' labels with their depth and the
novel views between the training poses (colour and labels, no depth), and prints, for each of the
four parts (the fit's steps, the semantic steps after them, label renders with depth, novel views),
the seconds spent in each phase, exclusive of the phases nested in it::

    python benchmarks/fit_profile.py synth:office:0 --frames 250 --size 160x120 --threads 2
    python benchmarks/fit_profile.py synth:apartment:0 --variant hard --ops

Phases are timed by wrapping the functions that make them (``time.perf_counter`` around
each call; on a CPU every operation is synchronous, so the clock is the cost):
``SemanticNerf.sample`` (ray sampling, the rendering march's density evaluations included),
the occupancy grid's update, the field evaluation and compositing (``render_samples``,
``render_samples_pruned``, ``render_semantics``), the hash encoding's forward and backward
(the C kernel of ``csa_core/nerf/hash_kernel.py``; 0 where the PyTorch path runs), the losses,
the autograd backward pass, Adam and the ray draws; ``other`` is what remains of the part
(Python, ``zero_grad``, the schedule, render bookkeeping). ``--ops`` also profiles 20 fit
steps with ``torch.profiler`` and prints the operators with the most self time.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from nerf_bench import load_scene

from csa_core.data.label_noise import corrupt_labels
from csa_core.data.scene import NYU40_FOLDER
from csa_core.data.synth import NOISY_FOLDER, degrade_scene, parse_size
from csa_core.nerf import fit_semantic_nerf, hash_kernel, render_views
from csa_core.nerf.model import SemanticNerf
from csa_core.nerf.rays import RayBank
from csa_core.nerf.samplers import RaySampler
from csa_core.nerf.trainer import NerfTrainer

LABELS = "label-fused-input"


class PhaseClock:
    """Exclusive seconds per (part, phase): a call's time minus that of the calls nested in it."""

    def __init__(self) -> None:
        self.seconds: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
        self.part = "outside"
        self._stack: list[list[float]] = []  # [start, seconds of nested calls]

    def timed(self, phase: str, fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            self._stack.append([time.perf_counter(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                start, nested = self._stack.pop()
                spent = time.perf_counter() - start
                self.seconds[self.part][phase] += spent - nested
                if self._stack:
                    self._stack[-1][1] += spent

        return wrapper

    def run(self, part: str, fn: Callable, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args)`` as the top of ``part``: its own time is ``other``."""
        previous, self.part = self.part, part
        try:
            return self.timed("other", fn)(*args, **kwargs)
        finally:
            self.part = previous


def install(clock: PhaseClock) -> None:
    """Wrap the phases' functions (class attributes, so objects made inside the fit see them)."""
    patches = [
        (SemanticNerf, "sample", "sampling (render march included)"),
        (SemanticNerf, "render_samples", "field + composite"),
        (SemanticNerf, "render_samples_pruned", "field + composite"),
        (SemanticNerf, "render_semantics", "field + composite"),
        (SemanticNerf, "losses", "losses"),
        (hash_kernel, "encode", "hash encoding forward (C kernel)"),
        (hash_kernel._KernelEncode, "backward", "hash encoding backward (C kernel)"),
        (torch.Tensor, "backward", "autograd backward (rest)"),
        (torch.optim.Adam, "step", "Adam"),
        (RayBank, "batch", "ray draws"),
        (RayBank, "balanced_ids", "ray draws"),
        (RayBank, "random_ids", "ray draws"),
    ]
    for owner, name, phase in patches:
        fn = owner.__dict__[name]
        if isinstance(fn, staticmethod):
            setattr(owner, name, staticmethod(clock.timed(phase, fn.__func__)))
        else:
            setattr(owner, name, clock.timed(phase, fn))
    for cls in [RaySampler, *RaySampler.__subclasses__()]:
        if "update_every_n_steps" in cls.__dict__:
            cls.update_every_n_steps = clock.timed(
                "occupancy grid update", cls.__dict__["update_every_n_steps"]
            )


def profile_ops(steps: int, rows: int) -> None:
    """Profile ``steps`` fit steps, from the 300th on, with ``torch.profiler``."""
    real = NerfTrainer.step
    state = {"n": 0, "prof": None}

    def step(self: NerfTrainer) -> Any:
        state["n"] += 1
        if state["n"] == 300:
            state["prof"] = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
            state["prof"].__enter__()
        out = real(self)
        if state["n"] == 300 + steps - 1:
            prof = state["prof"]
            prof.__exit__(None, None, None)
            print(f"\nfit steps 300-{300 + steps - 1} under torch.profiler, by self CPU time:")
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows))
        return out

    NerfTrainer.step = step


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "scene", nargs="?", default="synth:office:0", help="synth:FAMILY:SEED or folder:PATH"
    )
    p.add_argument("--variant", choices=("clean", "hard"), default="clean")
    p.add_argument("--frames", type=int, default=250)
    p.add_argument("--size", default="160x120")
    p.add_argument("--preset", default="fast")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--ops", action="store_true", help="also profile 20 fit steps with torch.profiler"
    )
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    scene, labelled = load_scene(args.scene, parse_size(args.size), args.frames)
    if not labelled or any(NYU40_FOLDER not in f.labels for f in scene.frames):
        raise SystemExit(f"{args.scene}: needs ground truth ({NYU40_FOLDER}) to corrupt")
    if args.variant == "hard":
        scene.frames = degrade_scene(
            scene, args.seed, source=NYU40_FOLDER, target=NOISY_FOLDER
        ).frames
        for f in scene.frames:
            f.labels[LABELS] = f.labels[NOISY_FOLDER]
    else:
        rng = np.random.default_rng(args.seed)
        for f in scene.frames:
            f.labels[LABELS] = corrupt_labels(f.labels[NYU40_FOLDER], rng)

    clock = PhaseClock()
    install(clock)
    if args.ops:
        profile_ops(20, 15)
    # The fit's two loops as their own parts (the semantic steps run inside the fit).
    real_step, real_semantic = NerfTrainer.step, NerfTrainer.semantic_steps
    NerfTrainer.step = lambda self: clock.run("fit steps", real_step, self)
    NerfTrainer.semantic_steps = lambda self, *a, **k: clock.run(
        "semantic steps", real_semantic, self, *a, **k
    )

    start = time.perf_counter()
    nerf, stats = fit_semantic_nerf(scene, LABELS, args.preset, device="cpu", progress=False)
    fit_wall = time.perf_counter() - start
    start = time.perf_counter()
    clock.run("labels with depth", render_views, nerf, scene, "train", semantics=True, color=False)
    with_depth = time.perf_counter() - start
    start = time.perf_counter()
    views = clock.run("novel views", render_views, nerf, None, "novel", semantics=True, color=True)
    novel = time.perf_counter() - start
    n_train = scene.num_train
    print(
        f"\n{args.scene} ({args.variant}), {len(scene)} frames at {args.size}, "
        f"preset {args.preset}, "
        f"{args.threads} threads, torch {torch.__version__}, C kernel: {hash_kernel.available()}"
    )
    print(
        f"fit {fit_wall:.1f} s ({stats.steps} steps), "
        f"labels with depth {with_depth / n_train:.3f} s per view ({n_train}), "
        f"novel views: {novel / len(views):.3f} s per view ({len(views)}, colour + labels)\n"
    )
    print("| part | phase | seconds | share of the part |")
    print("|---|---|---|---|")
    for part, phases in clock.seconds.items():
        total = sum(phases.values())
        for phase, s in sorted(phases.items(), key=lambda kv: -kv[1]):
            if s >= 0.0005 * total:
                print(f"| {part} | {phase} | {s:.2f} | {100 * s / total:.1f}% |")
        print(f"| {part} | **all** | **{total:.2f}** | |")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
