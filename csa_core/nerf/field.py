"""The Semantic-NeRF field: hash encoding -> density + geometry features -> colour and classes.

Positions are in the encoder's unit cube (``normalization.SceneBox.to_unit``); outside it the
density is zero. The renderer detaches the weights for the semantic channel (the paper's
stop-gradient; docs/method.md "Fuse in 3D"), and by default the semantic head reads the
geometry features *detached* too, so the semantic loss never shapes geometry; the official
head reads them undetached (``FieldConfig.semantic_detach_geometry=False``, the paper preset).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from csa_core.nerf.config import FieldConfig
from csa_core.nerf.hash_encoding import HashEncoding

# Above this the density's exponent is clipped: exp(88.7) overflows float32, and an infinite
# density times a zero-length interval made every parameter NaN in one step on a synthetic
# office captured from random viewpoints (step 742 of a `fast` fit; density logits reached 95).
# exp(30) = 1e13 per metre is opaque over any interval, so healthy fits never reach it.
MAX_DENSITY_LOGIT = 30.0


class _TruncExp(torch.autograd.Function):
    """exp(min(x, MAX_DENSITY_LOGIT)) whose gradient uses exp(clamp(x, -15, 15)): stable
    density activation (Instant-NGP's, with the forward kept finite)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=MAX_DENSITY_LOGIT))

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-15.0, 15.0))


def trunc_exp(x: Tensor) -> Tensor:
    return _TruncExp.apply(x)


def spherical_harmonics(dirs: Tensor, degree: int) -> Tensor:
    """Real spherical harmonics basis of unit directions ``(N, 3)`` -> ``(N, degree^2)``; degree
    1..4."""
    if not 1 <= degree <= 4:
        raise ValueError(f"spherical_harmonics: degree must be 1..4, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.94617469575756008 * zz - 0.31539156525252005,
            -1.0925484305920792 * xz,
            0.54627421529603959 * (xx - yy),
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * xy * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def _mlp(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers):
        # In place: a linear layer's backward needs its input, not its output, so autograd
        # allows it, and it saves a pass over every hidden activation (MLP forward -17% when
        # rendering: benchmarks/results/speed.md, "Fewer band samples and one corner layout").
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, out_dim))
    return nn.Sequential(*mods)


class SemanticField(nn.Module):
    """Density, colour (view dependent) and semantic logits at points of the unit cube."""

    def __init__(self, cfg: FieldConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.cfg = cfg
        self.encoding = HashEncoding(cfg.encoding, generator=generator)
        self.density_mlp = _mlp(
            self.encoding.out_dim, cfg.hidden_dim, cfg.density_hidden_layers, 1 + cfg.geo_features
        )
        self.color_mlp = _mlp(
            cfg.sh_degree**2 + cfg.geo_features, cfg.hidden_dim, cfg.color_hidden_layers, 3
        )
        self.semantic_levels = min(cfg.semantic_grid_levels, cfg.encoding.num_levels)
        self.semantic_table = None
        if self.semantic_levels > 0:
            rows = self.encoding.level_rows(self.semantic_levels)
            self.semantic_table = nn.Parameter(torch.zeros(rows, cfg.encoding.features_per_level))
        sem_in = cfg.geo_features + self.semantic_levels * cfg.encoding.features_per_level
        self.semantic_mlp = _mlp(
            sem_in, cfg.hidden_dim, cfg.semantic_hidden_layers, cfg.num_classes
        )

    def geometry_parameters(self) -> list[nn.Parameter]:
        """Parameters that shape density (the hash table and the density MLP)."""
        return [*self.encoding.parameters(), *self.density_mlp.parameters()]

    def features(self, x: Tensor, semantic_features: bool) -> tuple[Tensor, Tensor, Tensor | None]:
        """Density ``(N,)``, geometry features and (with ``semantic_features``) the semantic
        table's features at ``x``, the cell corners found once for both tables."""
        if semantic_features and self.semantic_table is not None:
            enc, sem = self.encoding(x, self.semantic_table, self.semantic_levels)
        else:
            enc, sem = self.encoding(x), None
        sigma, geo = self._density_head(x, enc)
        return sigma, geo, sem

    def _run(self, mlp: nn.Module, inputs: Tensor) -> Tensor:
        """``mlp(inputs)``, under bf16 autocast on CUDA with ``FieldConfig.mlp_dtype``
        "bfloat16" (the result back in float32)."""
        if self.cfg.mlp_dtype == "bfloat16" and inputs.is_cuda:
            with torch.autocast("cuda", dtype=torch.bfloat16):
                return mlp(inputs).float()
        return mlp(inputs)

    def _density_head(self, x: Tensor, enc: Tensor) -> tuple[Tensor, Tensor]:
        h = self._run(self.density_mlp, enc)
        inside = ((x >= 0) & (x <= 1)).all(dim=-1)
        sigma = trunc_exp(h[:, 0] - 1.0) * inside  # bias -1: start nearly empty
        return sigma, h[:, 1:]

    def semantic_head(self, geo: Tensor, sem: Tensor | None) -> Tensor:
        """Semantic logits from geometry features (detached unless
        ``FieldConfig.semantic_detach_geometry`` is off) and semantic-table features."""
        if self.cfg.semantic_detach_geometry:
            geo = geo.detach()
        sem_in = geo if sem is None else torch.cat([geo, sem], dim=-1)
        return self._run(self.semantic_mlp, sem_in)

    def density(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Density ``(N,)`` (per metre of world space) and geometry features ``(N, geo)`` at
        ``x``."""
        sigma, geo, _ = self.features(x, semantic_features=False)
        return sigma, geo

    def semantics(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Density ``(N,)`` without gradient and semantic logits ``(N, num_classes)`` at ``x``:
        the semantic head alone, for training it with geometry frozen. The cell corners are
        found once for both tables; only the semantic table and MLP see gradients."""
        if self.semantic_table is None:
            with torch.no_grad():
                sigma, geo = self.density(x)
            return sigma, self.semantic_head(geo, None)
        enc, sem = self.encoding(x, self.semantic_table, self.semantic_levels, detach_main=True)
        with torch.no_grad():
            sigma, geo = self._density_head(x, enc)
        return sigma, self.semantic_head(geo, sem)

    def color(self, geo: Tensor, dirs: Tensor) -> Tensor:
        """Colour ``(N, 3)`` in [0, 1] from geometry features and unit view directions."""
        sh = spherical_harmonics(dirs, self.cfg.sh_degree)
        return torch.sigmoid(self._run(self.color_mlp, torch.cat([sh, geo], dim=-1)))

    def forward(
        self, x: Tensor, dirs: Tensor | None, semantics: bool = True, color: bool = True
    ) -> dict[str, Tensor]:
        """``x`` (N, 3) unit-cube points, ``dirs`` (N, 3) unit view directions.

        Returns ``sigma`` (N,), with ``color`` ``rgb`` (N, 3) in [0, 1] and, with ``semantics``,
        ``semantic_logits`` (N, num_classes) computed from detached geometry features.
        ``dirs`` may be ``None`` without ``color`` (labels do not depend on the view).
        """
        sigma, geo, sem = self.features(x, semantic_features=semantics)
        out = {"sigma": sigma}
        if color:
            if dirs is None:
                raise ValueError("SemanticField: colour needs view directions")
            out["rgb"] = self.color(geo, dirs)
        if semantics:
            out["semantic_logits"] = self.semantic_head(geo, sem)
        return out
