"""The semantic loss of the ablation: Semantic-NeRF's original (softmax cross-entropy of the
composited logits) beside the paper's (NLL of the normalised class distribution, Eq. 3-4),
chosen by ``LossConfig.semantic_form``."""

from __future__ import annotations

import math

import pytest
import torch

from csa_core.nerf.config import FieldConfig, HashEncodingConfig, LossConfig
from csa_core.nerf.field import SemanticField
from csa_core.nerf.losses import (
    band_consistency_loss,
    semantic_cross_entropy,
    semantic_loss,
    total_loss,
)
from csa_core.nerf.rendering import RaySamples, class_distribution, render_weights


def two_rays() -> tuple[RaySamples, torch.Tensor, torch.Tensor]:
    """Two rays of two samples each, with rendering weights and 40 logits per sample."""
    samples = RaySamples(
        torch.tensor([0, 0, 1, 1]),
        torch.tensor([0.0, 1.0, 0.0, 1.0]),
        torch.tensor([1.0, 2.0, 1.0, 2.0]),
        2,
        per_ray=2,
    )
    weights = torch.tensor([0.5, 0.25, 0.1, 0.8])
    logits = torch.zeros(4, 40)
    logits[0, 2] = 2.0  # ray 0, first sample: class id 3
    logits[1, 6] = 4.0  # ray 0, second sample: class id 7
    logits[2, 0] = 1.0  # ray 1: class id 1 in front ...
    logits[3, 39] = 3.0  # ... and id 40 behind
    return samples, weights, logits


def test_the_original_loss_is_the_cross_entropy_of_the_composited_logits_by_hand():
    samples, weights, logits = two_rays()
    probs, composited = class_distribution(weights, logits, samples, "semantic_nerf")
    # Ray 0: 0.5 * logits[0] + 0.25 * logits[1]: channel 2 -> 1.0, channel 6 -> 1.0, else 0.
    # Ray 1: 0.1 * logits[2] + 0.8 * logits[3]: channel 0 -> 0.1, channel 39 -> 2.4, else 0.
    expected = torch.zeros(2, 40)
    expected[0, 2], expected[0, 6] = 1.0, 1.0
    expected[1, 0], expected[1, 39] = 0.1, 2.4
    torch.testing.assert_close(composited, expected)
    torch.testing.assert_close(probs.sum(-1), torch.ones(2))
    labels = torch.tensor([7, 1])  # ids: channel 6 for ray 0, channel 0 for ray 1
    ce0 = -1.0 + math.log(2 * math.e + 38)  # -log(e^1 / (2 e^1 + 38 e^0))
    ce1 = -0.1 + math.log(math.exp(0.1) + math.exp(2.4) + 38)
    by_hand = (ce0 + ce1) / 2
    assert float(semantic_cross_entropy(composited, labels)) == pytest.approx(by_hand, rel=1e-6)
    # Unknown (0) labels are ignored: ray 1 alone.
    assert float(semantic_cross_entropy(composited, torch.tensor([0, 1]))) == pytest.approx(
        ce1, rel=1e-6
    )
    # The loss of the config's form in the fit's total: colour 0, so the semantic term alone.
    out = {"rgb": torch.zeros(2, 3), "semantics": probs, "semantic_logits": composited}
    batch = {"rgb": torch.zeros(2, 3), "labels": labels}
    terms = total_loss(out, batch, LossConfig(semantic_form="semantic_nerf", depth=0.0))
    assert float(terms["semantic"]) == pytest.approx(by_hand, rel=1e-6)
    assert float(terms["loss"]) == pytest.approx(0.04 * by_hand, rel=1e-6)


def test_the_two_forms_differ_and_the_paper_form_is_eq_3_4():
    samples, weights, logits = two_rays()
    labels = torch.tensor([7, 1])
    paper, none = class_distribution(weights, logits, samples, "paper")
    original, composited = class_distribution(weights, logits, samples, "semantic_nerf")
    assert none is None and composited is not None
    # Eq. 3 by hand for ray 0: weighted per-sample softmaxes, normalised.
    p0 = 0.5 * torch.softmax(logits[0], -1) + 0.25 * torch.softmax(logits[1], -1)
    torch.testing.assert_close(paper[0], p0 / p0.sum())
    nll = float(semantic_loss(paper, labels))
    ce = float(semantic_cross_entropy(composited, labels))
    assert abs(nll - ce) > 0.1 and not torch.allclose(paper, original, atol=1e-3)
    terms = {
        form: float(
            total_loss(
                {"rgb": torch.zeros(2, 3), "semantics": p, "semantic_logits": composited},
                {"rgb": torch.zeros(2, 3), "labels": labels},
                LossConfig(semantic_form=form),
            )["semantic"]
        )
        for form, p in (("paper", paper), ("semantic_nerf", original))
    }
    assert terms == {"paper": pytest.approx(nll), "semantic_nerf": pytest.approx(ce)}


def test_gradients_reach_the_semantic_head_and_not_the_density_in_both_forms():
    enc = HashEncodingConfig(
        num_levels=4, log2_table_size=12, base_resolution=4, finest_resolution=64
    )
    grads = {}
    for form in ("paper", "semantic_nerf"):
        field = SemanticField(FieldConfig(encoding=enc), generator=torch.Generator().manual_seed(0))
        n_rays, k = 6, 10
        t = torch.linspace(0.1, 0.9, k + 1)
        samples = RaySamples(
            torch.arange(n_rays).repeat_interleave(k),
            t[:-1].repeat(n_rays),
            t[1:].repeat(n_rays),
            n_rays,
            per_ray=k,
        )
        g = torch.Generator().manual_seed(1)
        x = torch.rand(n_rays, 1, 3, generator=g) * 0.5 + torch.linspace(0, 0.4, k).view(1, k, 1)
        dirs = torch.nn.functional.normalize(torch.randn(n_rays * k, 3, generator=g), dim=-1)
        out = field(x.reshape(-1, 3), dirs)
        w, _, _ = render_weights(out["sigma"], samples)
        probs, composited = class_distribution(w, out["semantic_logits"], samples, form)
        labels = torch.tensor([1, 5, 0, 40, 12, 3])
        loss = (
            semantic_loss(probs, labels)
            if form == "paper"
            else semantic_cross_entropy(composited, labels)
        )
        loss.backward()
        named = dict(field.named_parameters())
        sem = [p.grad for n, p in named.items() if n.startswith("semantic_mlp.")]
        assert sem and all(gr is not None for gr in sem)
        assert sum(float(gr.abs().sum()) for gr in sem) > 0
        density = [p.grad for n, p in named.items() if n.startswith("density_mlp.")]
        # The stop-gradient holds in both forms: the density MLP gets no semantic gradient.
        assert all(gr is None or float(gr.abs().sum()) == 0.0 for gr in density)
        grads[form] = torch.cat([gr.flatten() for gr in sem])
    assert not torch.allclose(grads["paper"], grads["semantic_nerf"])


def test_a_fit_with_the_original_loss_trains_and_renders_labels(workspace):
    """Both loss paths of a fit (its steps and the semantic-head steps after it) run with the
    original loss, and the rendered labels are the composited logits' argmax."""
    import numpy as np

    from csa_core.adapt.config import preset
    from csa_core.adapt.pseudo_labels import label_miou, nerf_config, render_pairs
    from csa_core.data.scene_io import read_scene
    from csa_core.nerf.fit import fit_semantic_nerf

    scene = read_scene(workspace.scenes[0])
    results = {}
    for form in ("paper", "semantic_nerf"):
        cfg = nerf_config(preset("tiny").nerf)
        cfg.loss.semantic_form = form
        nerf, stats = fit_semantic_nerf(scene, "label-nyu40", cfg, steps=40, progress=False)
        assert math.isfinite(stats.final_loss)
        _, labels = render_pairs(nerf, scene, color=False)
        results[form] = (label_miou(labels, scene), labels)
    for miou, _labels in results.values():
        assert 0.0 < miou <= 1.0
    differs = any(
        not np.array_equal(results["paper"][1][n], results["semantic_nerf"][1][n])
        for n in results["paper"][1]
    )
    assert differs


def test_an_unknown_form_names_the_field():
    with pytest.raises(ValueError, match="loss.semantic_form must be one of paper, semantic_nerf"):
        LossConfig(semantic_form="softmax")
    from csa_core.adapt.config import preset
    from csa_core.errors import CSAInputError
    from csa_core.overrides import apply_overrides

    with pytest.raises((CSAInputError, ValueError), match="semantic_form"):
        apply_overrides(preset("tiny"), ["nerf.preset_overrides=('loss.semantic_form=softmax',)"])


def _ce(logits: torch.Tensor, channel: int) -> float:
    return float(torch.nn.functional.cross_entropy(logits[None], torch.tensor([channel])))


def test_the_band_consistency_term_asks_every_weighted_sample_for_the_label_by_hand():
    """``loss.semantic_band_consistency``: per ray, the samples' own cross-entropies averaged
    with their weights normalised over the ray; the mean over labelled rays, importance
    weights as in the composited terms."""
    samples, weights, logits = two_rays()
    labels = torch.tensor([7, 1])
    ray0 = (0.5 * _ce(logits[0], 6) + 0.25 * _ce(logits[1], 6)) / 0.75
    ray1 = (0.1 * _ce(logits[2], 0) + 0.8 * _ce(logits[3], 0)) / 0.9
    value = band_consistency_loss(logits, weights, samples, labels)
    assert float(value) == pytest.approx((ray0 + ray1) / 2, rel=1e-6)
    weighted = band_consistency_loss(logits, weights, samples, labels, torch.tensor([3.0, 1.0]))
    assert float(weighted) == pytest.approx((3 * ray0 + ray1) / 4, rel=1e-6)
    # Unknown labels and rays without weight have no term.
    assert float(band_consistency_loss(logits, weights, samples, torch.tensor([0, 1]))) == (
        pytest.approx(ray1, rel=1e-6)
    )
    empty = torch.tensor([0.0, 0.0, 0.1, 0.8])
    assert float(band_consistency_loss(logits, empty, samples, labels)) == pytest.approx(
        ray1, rel=1e-6
    )


def test_the_band_consistency_term_sees_a_label_left_to_one_sample_of_the_ray():
    """A ray whose front sample says one class and whose back sample another can render the
    label the view gave under the composited terms: the consistency term charges the sample
    that disagrees, and its gradient reaches each sample's logits in proportion to its weight."""
    samples = RaySamples(
        torch.tensor([0, 0]), torch.tensor([0.0, 1.0]), torch.tensor([1.0, 2.0]), 1, per_ray=2
    )
    weights = torch.tensor([0.2, 0.8])
    logits = torch.zeros(2, 40)
    logits[0, 21] = 8.0  # front: id 22 (ceiling)
    logits[1, 18] = 8.0  # behind: id 19 (mirror)
    logits.requires_grad_(True)
    label = torch.tensor([19])
    _, composited = class_distribution(weights, logits, samples, "semantic_nerf")
    assert float(semantic_cross_entropy(composited, label).detach()) < 0.1  # the label rendered
    value = band_consistency_loss(logits, weights, samples, label)
    front_ce, back_ce = _ce(logits[0].detach(), 18), _ce(logits[1].detach(), 18)
    assert float(value.detach()) == pytest.approx(0.2 * front_ce + 0.8 * back_ce, rel=1e-5)
    assert 0.2 * front_ce > 100 * 0.8 * back_ce
    value.backward()
    front, back = logits.grad[0], logits.grad[1]
    assert front[18] < -0.19  # the disagreeing sample is pulled towards the label
    assert back.abs().max() < 0.02  # the agreeing one is nearly there


def test_the_fit_and_the_semantic_steps_add_the_band_consistency_term_when_asked(workspace):
    """With ``loss.semantic_band_consistency`` a fit step's terms hold it, weighed by the
    semantic weight times the option, and the semantic-head steps run with it; off, no
    term and no per-sample logits are kept."""
    from csa_core.adapt.config import preset
    from csa_core.adapt.pseudo_labels import nerf_config
    from csa_core.data.scene_io import read_scene
    from csa_core.nerf.fit import fit_semantic_nerf
    from csa_core.nerf.rays import RayBank
    from csa_core.nerf.trainer import NerfTrainer

    scene = read_scene(workspace.scenes[0])
    for weight in (0.0, 2.0):
        cfg = nerf_config(preset("tiny").nerf)
        cfg.loss.semantic_form = "semantic_nerf"
        cfg.loss.semantic_band_consistency = weight
        nerf, _ = fit_semantic_nerf(scene, "label-nyu40", cfg, steps=10, progress=False)
        bank = RayBank(scene.frames, scene.intrinsics, label_folder="label-nyu40")
        trainer = NerfTrainer(nerf, bank, 5, seed=0)
        terms = {k: float(v.detach()) for k, v in trainer.step().items()}
        if weight == 0:
            assert "band_consistency" not in terms
            continue
        consistency = terms["band_consistency"]
        assert consistency > 0
        rest = sum(
            cfg.loss.__dict__[k] * terms[k] for k in ("color", "depth", "semantic")
        ) + cfg.loss.free_space * terms.get("free_space", 0.0)
        assert terms["loss"] == pytest.approx(
            rest + cfg.loss.semantic * weight * consistency, rel=1e-5
        )
        assert math.isfinite(trainer.semantic_steps(3, rays_per_step=64))
