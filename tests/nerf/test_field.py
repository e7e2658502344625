"""The field and the losses: shapes, activations, and where gradients stop."""

from __future__ import annotations

import torch

from csa_core.nerf.config import FieldConfig, HashEncodingConfig, LossConfig
from csa_core.nerf.field import SemanticField, spherical_harmonics, trunc_exp
from csa_core.nerf.losses import depth_loss, semantic_loss, total_loss
from csa_core.nerf.rendering import (
    RaySamples,
    accumulate_along_rays,
    normalized_class_probabilities,
    render_weights,
)


def _small_field() -> SemanticField:
    enc = HashEncodingConfig(
        num_levels=4, log2_table_size=12, base_resolution=4, finest_resolution=64
    )
    return SemanticField(FieldConfig(encoding=enc), generator=torch.Generator().manual_seed(0))


def _render(field: SemanticField, n_rays: int = 8, k: int = 12):
    g = torch.Generator().manual_seed(1)
    t = torch.linspace(0.1, 0.9, k + 1)
    samples = RaySamples(
        torch.arange(n_rays).repeat_interleave(k),
        t[:-1].repeat(n_rays),
        t[1:].repeat(n_rays),
        n_rays,
        per_ray=k,
    )
    x = torch.rand(n_rays, 1, 3, generator=g) * 0.5 + torch.linspace(0, 0.4, k).view(1, k, 1)
    dirs = torch.nn.functional.normalize(torch.randn(n_rays * k, 3, generator=g), dim=-1)
    out = field(x.reshape(-1, 3), dirs)
    w, _, _ = render_weights(out["sigma"], samples)
    return {
        "rgb": accumulate_along_rays(w, out["rgb"], samples),
        "depth": accumulate_along_rays(w, samples.t_mids[:, None], samples).squeeze(-1),
        "semantics": normalized_class_probabilities(w, out["semantic_logits"], samples),
    }


def test_semantic_loss_does_not_move_geometry_or_colour():
    field = _small_field()
    with torch.no_grad():  # make density non-trivial so weights are not ~0
        field.density_mlp[-1].bias[0] = 3.0
    out = _render(field)
    labels = torch.tensor([1, 5, 0, 40, 12, 12, 3, 7])
    semantic_loss(out["semantics"], labels).backward()
    for name, p in field.named_parameters():
        grad = torch.zeros(()) if p.grad is None else p.grad.abs().sum()
        if name.startswith("semantic_mlp") or name == "semantic_table":
            continue
        assert grad == 0, f"semantic loss reached {name}"
    assert sum(float(p.grad.abs().sum()) for p in field.semantic_mlp.parameters()) > 0
    assert field.semantic_table.grad.abs().sum() > 0


def test_paper_semantic_head_reads_geometry_features_only():
    enc = HashEncodingConfig(
        num_levels=4, log2_table_size=12, base_resolution=4, finest_resolution=64
    )
    field = SemanticField(FieldConfig(encoding=enc, semantic_grid_levels=0))
    assert field.semantic_table is None
    assert field.semantic_mlp[0].in_features == 15
    out = field(torch.rand(5, 3), torch.nn.functional.normalize(torch.randn(5, 3), dim=-1))
    assert out["semantic_logits"].shape == (5, 40)


def test_colour_and_depth_losses_train_the_geometry():
    field = _small_field()
    out = _render(field)
    batch = {
        "rgb": torch.rand(8, 3),
        "depth": torch.full((8,), 0.5),
        "labels": torch.ones(8, dtype=torch.long),
    }
    terms = total_loss(out, batch, LossConfig())
    terms["loss"].backward()
    assert field.encoding.table.grad.abs().sum() > 0
    assert field.density_mlp[0].weight.grad.abs().sum() > 0
    assert set(terms) == {"color", "depth", "semantic", "loss"}
    expected = terms["color"] + 0.1 * terms["depth"] + 0.04 * terms["semantic"]
    torch.testing.assert_close(terms["loss"], expected)


def test_unknown_labels_and_missing_depth_are_ignored():
    probs = torch.full((3, 40), 1 / 40)
    probs_known = semantic_loss(probs, torch.tensor([0, 0, 4]))
    torch.testing.assert_close(probs_known, torch.log(torch.tensor(40.0)))
    assert float(semantic_loss(probs, torch.zeros(3, dtype=torch.long))) == 0.0
    pred = torch.tensor([1.0, 2.0, 3.0])
    torch.testing.assert_close(depth_loss(pred, torch.tensor([0.0, 2.5, 0.0])), torch.tensor(0.5))
    assert float(depth_loss(pred, torch.zeros(3))) == 0.0


def test_label_channels_map_to_nyu40_ids():
    probs = torch.zeros(2, 40)
    probs[0, 0] = 1.0  # channel 0 = id 1 (wall)
    probs[1, 39] = 1.0  # channel 39 = id 40 (otherprop)
    assert float(semantic_loss(probs, torch.tensor([1, 40]))) < 1e-6
    assert float(semantic_loss(probs, torch.tensor([2, 39]))) > 10


def test_density_is_zero_outside_the_unit_cube_and_trunc_exp_is_stable():
    field = _small_field()
    x = torch.tensor([[0.5, 0.5, 0.5], [1.2, 0.5, 0.5], [-0.1, 0.2, 0.3]])
    sigma, geo = field.density(x)
    assert sigma[0] > 0 and sigma[1] == 0 and sigma[2] == 0
    assert geo.shape == (3, 15)
    z = torch.tensor([100.0], requires_grad=True)
    trunc_exp(z).backward()
    assert torch.isfinite(z.grad).all()


def test_an_overflowing_density_renders_finite_weights():
    """A density logit past float32's exp range on a zero-length interval (depth-guided
    samples can touch) once made a whole fit NaN: the forward is clipped, so weights and
    gradients stay finite, and ordinary logits are untouched."""
    logits = torch.tensor([5.0, 95.0, 95.0, 2.0], requires_grad=True)
    sigma = trunc_exp(logits)
    assert torch.isfinite(sigma).all()
    assert sigma[0] == torch.exp(torch.tensor(5.0)) and sigma[3] == torch.exp(torch.tensor(2.0))
    samples = RaySamples(
        torch.zeros(4, dtype=torch.long), torch.tensor([0.0, 1.0, 1.0, 2.0]),
        torch.tensor([1.0, 1.0, 1.5, 3.0]), num_rays=1,
    )  # fmt: skip
    weights, _, _ = render_weights(sigma, samples)
    weights.sum().backward()
    assert torch.isfinite(weights).all() and torch.isfinite(logits.grad).all()


def test_spherical_harmonics_shapes_and_constant_term():
    d = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    for deg in (1, 2, 3, 4):
        sh = spherical_harmonics(d, deg)
        assert sh.shape == (10, deg * deg)
    torch.testing.assert_close(
        spherical_harmonics(d, 4)[:, 0], torch.full((10,), 0.28209479177387814)
    )


def test_the_official_semantic_head_lets_the_semantic_loss_reach_the_geometry_features():
    """``semantic_detach_geometry=False`` (the official code's; the ``paper-official``
    preset): the semantic loss reaches the
    density MLP and the hash table through the features, never the colour head; the
    rendering weights stay detached (only the features carry it)."""
    enc = HashEncodingConfig(
        num_levels=4, log2_table_size=12, base_resolution=4, finest_resolution=64
    )
    cfg = FieldConfig(encoding=enc, semantic_grid_levels=0, semantic_detach_geometry=False)
    field = SemanticField(cfg, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        field.density_mlp[-1].bias[0] = 3.0
    out = _render(field)
    semantic_loss(out["semantics"], torch.tensor([1, 5, 0, 40, 12, 12, 3, 7])).backward()
    grads = {
        n: (0.0 if p.grad is None else float(p.grad.abs().sum()))
        for n, p in field.named_parameters()
    }
    assert grads["encoding.table"] > 0
    assert sum(g for n, g in grads.items() if n.startswith("density_mlp")) > 0
    assert all(g == 0 for n, g in grads.items() if n.startswith("color_mlp"))
    # The density output itself gets no semantic gradient: its row of the last layer is untouched.
    assert float(field.density_mlp[-1].weight.grad[0].abs().sum()) == 0.0
