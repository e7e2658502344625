"""BatchNorm statistics of every adapted scene, pooled so one network serves them all.

Each step ends with AdaBN on the current scene's camera images, so after step i the network
normalises with scene i's statistics only. A network trained from scratch is very sensitive
to them: in the demo's first continual run (3 synthetic offices) scene 0 scored 30.8% mIoU
right after its step and 21.9% after step 2, and the mean over the scenes after the last
step fell below the pre-trained network's. The statistics are the suspect: AdaBN alone (no
training) moved scene 0 from 22.0% to 31.9%. Keeping each scene's statistics (a
few KB per scene, beside its NeRF) and running with their pooled mixture treats every
adapted scene alike, much as AdaBN over the union of their images would (exactly so for the
first BatchNorm layer; deeper ones saw per-scene normalised inputs), without storing images.

The mixture gives each scene equal weight: mean = avg_k(mean_k) and
var = avg_k(var_k + mean_k^2) - mean^2 (the variance of the pooled distribution).

The memory travels between processes (the service's adapt jobs) as one safetensors file:
tensors ``<scene index>.<layer index>.mean`` / ``.var`` and, in the header, the scene names
in the order they were recorded (the order fixes the mixture's floating-point sums).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as st_save
from torch import Tensor, nn

from csa_core.atomic_io import write_bytes_atomic
from csa_core.errors import CSAInputError
from csa_core.seg.adabn import batchnorm_layers

FORMAT = "csa-batchnorm-memory"
VERSION = 1


class BatchNormMemory:
    """Per-scene BatchNorm running statistics, and their pooled mixture."""

    def __init__(self) -> None:
        self.scenes: dict[str, list[tuple[Tensor, Tensor]]] = {}

    def add(self, scene: str, model: nn.Module) -> None:
        """Record ``model``'s current statistics as ``scene``'s (replacing an earlier record)."""
        self.scenes[scene] = [
            (bn.running_mean.detach().clone(), bn.running_var.detach().clone())  # type: ignore[union-attr]
            for bn in batchnorm_layers(model)
        ]

    def nbytes(self) -> int:
        return sum(
            m.numel() * m.element_size() + v.numel() * v.element_size()
            for s in self.scenes.values()
            for m, v in s
        )

    @torch.no_grad()
    def apply(self, model: nn.Module) -> None:
        """Set ``model``'s statistics to the equal-weight mixture of the recorded scenes'
        (with one record: that record exactly). Raises ``ValueError`` when the records do
        not fit ``model``'s BatchNorm layers."""
        if not self.scenes:
            return
        layers = batchnorm_layers(model)
        records = list(self.scenes.values())
        for name, record in self.scenes.items():
            shapes = [tuple(m.shape) for m, _ in record]
            if shapes != [tuple(bn.running_mean.shape) for bn in layers]:  # type: ignore[union-attr]
                raise ValueError(
                    f"BatchNorm memory: the record of scene {name!r} has {len(shapes)} layers "
                    f"that do not match the network's {len(layers)} BatchNorm layers"
                )
        for k, bn in enumerate(layers):
            device = bn.running_mean.device  # type: ignore[union-attr]
            if len(records) == 1:  # the mixture of one record is that record, bit for bit
                bn.running_mean.copy_(records[0][k][0])  # type: ignore[union-attr]
                bn.running_var.copy_(records[0][k][1])  # type: ignore[union-attr]
                continue
            means = torch.stack([r[k][0].to(device) for r in records])
            variances = torch.stack([r[k][1].to(device) for r in records])
            mean = means.mean(dim=0)
            var = (variances + means.square()).mean(dim=0) - mean.square()
            bn.running_mean.copy_(mean)  # type: ignore[union-attr]
            bn.running_var.copy_(var.clamp_min(0.0))  # type: ignore[union-attr]

    def to_bytes(self) -> bytes:
        """The memory as safetensors bytes (float tensors on the CPU, scene order in the header)."""
        tensors = {
            f"{i}.{k}.{what}": t.detach().to("cpu").contiguous()
            for i, record in enumerate(self.scenes.values())
            for k, pair in enumerate(record)
            for what, t in zip(("mean", "var"), pair, strict=True)
        }
        meta = {"format": FORMAT, "version": VERSION, "scenes": list(self.scenes)}
        return st_save(tensors, metadata={"csa": json.dumps(meta)})

    def save(self, path: str | Path) -> int:
        """Write the memory to ``path`` atomically (safetensors, never pickle); returns its size."""
        data = self.to_bytes()
        write_bytes_atomic(path, data)
        return len(data)

    @classmethod
    def load(cls, path: str | Path) -> BatchNormMemory:
        """Read a memory written by :meth:`save` (tensors on the CPU); a damaged or foreign
        file raises :class:`~csa_core.errors.CSAInputError` naming it."""
        path = Path(path)
        if not path.is_file():
            raise CSAInputError(path, "BatchNorm memory not found")
        try:
            with safe_open(path, framework="pt") as f:
                meta = json.loads((f.metadata() or {}).get("csa", "{}"))
                tensors = {key: f.get_tensor(key) for key in f.keys()}  # noqa: SIM118
        except (SafetensorError, OSError, ValueError) as e:
            raise CSAInputError(
                path, f"not a readable BatchNorm memory ({type(e).__name__}: {e})"
            ) from None
        try:
            return cls._from_tensors(meta, tensors)
        except ValueError as e:
            raise CSAInputError(path, str(e)) from None

    @classmethod
    def _from_tensors(cls, meta: dict, tensors: dict[str, Tensor]) -> BatchNormMemory:
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise ValueError(
                f"format is {meta.get('format')!r} version {meta.get('version')!r}, "
                f"expected {FORMAT!r} version {VERSION}"
            )
        names = meta.get("scenes")
        if not isinstance(names, list) or not all(isinstance(x, str) for x in names):
            raise ValueError("the header's scene list is not a list of names")
        if len(set(names)) != len(names):
            raise ValueError(f"repeated scene names in {names}")
        layers = sum(1 for key in tensors if key.startswith("0.") and key.endswith(".mean"))
        expected = {
            f"{i}.{k}.{what}"
            for i in range(len(names))
            for k in range(layers)
            for what in ("mean", "var")
        }
        if set(tensors) != expected:
            odd = sorted(set(tensors) ^ expected)[:4]
            raise ValueError(
                f"expected mean and var of {layers} layers for each of {len(names)} scenes; "
                f"tensors out of place: {', '.join(odd)}"
            )
        memory = cls()
        for i, name in enumerate(names):
            record = []
            for k in range(layers):
                mean, var = tensors[f"{i}.{k}.mean"], tensors[f"{i}.{k}.var"]
                if mean.shape != var.shape or mean.ndim != 1 or not mean.is_floating_point():
                    raise ValueError(
                        f"scene {name!r} layer {k}: mean {tuple(mean.shape)} and var "
                        f"{tuple(var.shape)} are not two float vectors of one size"
                    )
                if i > 0 and mean.shape != memory.scenes[names[0]][k][0].shape:
                    raise ValueError(
                        f"scene {name!r} layer {k} has {mean.numel()} channels, scene "
                        f"{names[0]!r} {memory.scenes[names[0]][k][0].numel()}"
                    )
                record.append((mean, var))
            memory.scenes[name] = record
        return memory
