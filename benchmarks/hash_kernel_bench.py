"""The hash encoding through the fused C kernel against the PyTorch path, side by side.

Interleaved repetitions in one process (kernel, PyTorch, kernel, ...), medians, on the `fast`
preset's encoding (16 levels x 2 features, 2^15 table, finest resolution 1024) and its field
(with the semantic table). Prints one Markdown table (not a test)::

    python benchmarks/hash_kernel_bench.py --threads 2 --repeats 7

Rows: the encoding alone without gradients (a render's block of samples), the encoding
forward + backward (a fit step's samples), the field forward + backward of a fit step (density,
colour and semantic heads), a semantic-only step (``SemanticField.semantics``, gradients to the
semantic table and head), and a render's field evaluation (``SemanticField.features``).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

from csa_core.nerf import hash_kernel
from csa_core.nerf.config import preset
from csa_core.nerf.field import SemanticField


def _fields() -> tuple[SemanticField, SemanticField]:
    cfg = preset("fast").field
    kernel = SemanticField(cfg, generator=torch.Generator().manual_seed(0))
    torch_cfg = preset("fast").field
    torch_cfg.encoding.implementation = "torch"
    reference = SemanticField(torch_cfg)
    reference.load_state_dict(kernel.state_dict())
    return kernel, reference


def _cases(gen: torch.Generator) -> list[tuple[str, int, Callable[[SemanticField, int], None]]]:
    def encode(f: SemanticField, n: int) -> None:
        with torch.inference_mode():
            f.encoding(torch.rand(n, 3, generator=gen))

    def encode_backward(f: SemanticField, n: int) -> None:
        f.encoding(torch.rand(n, 3, generator=gen)).sum().backward()

    def fit_step(f: SemanticField, n: int) -> None:
        x = torch.rand(n, 3, generator=gen)
        d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
        out = f(x, d)
        (out["sigma"].sum() + out["rgb"].sum() + out["semantic_logits"].sum()).backward()

    def semantic_step(f: SemanticField, n: int) -> None:
        _, logits = f.semantics(torch.rand(n, 3, generator=gen))
        logits.sum().backward()

    def render(f: SemanticField, n: int) -> None:
        with torch.inference_mode():
            f.features(torch.rand(n, 3, generator=gen), semantic_features=True)

    return [
        ("encoding, no gradients", 131072, encode),
        ("encoding, forward + backward", 16384, encode_backward),
        ("field, a fit step's forward + backward", 16384, fit_step),
        ("field, a semantic-only step", 65536, semantic_step),
        ("field, a render's evaluation", 131072, render),
    ]


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=7)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if not hash_kernel.available():
        raise SystemExit("the C kernel cannot be built here (no C compiler): nothing to compare")
    kernel, reference = _fields()
    gen = torch.Generator().manual_seed(0)
    print(f"{args.threads} threads, {args.repeats} interleaved repetitions, medians")
    print("| what | samples | C kernel ms | PyTorch ms | PyTorch / kernel |")
    print("|---|---|---|---|---|")
    for name, n, fn in _cases(gen):
        fn(kernel, n), fn(reference, n)  # warm-up
        times: dict[str, list[float]] = {"kernel": [], "torch": []}
        for _ in range(args.repeats):
            for key, f in (("kernel", kernel), ("torch", reference)):
                f.zero_grad(set_to_none=True)
                t0 = time.perf_counter()
                fn(f, n)
                times[key].append(time.perf_counter() - t0)
        k, t = statistics.median(times["kernel"]), statistics.median(times["torch"])
        print(f"| {name} | {n} | {1e3 * k:.1f} | {1e3 * t:.1f} | {t / k:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
