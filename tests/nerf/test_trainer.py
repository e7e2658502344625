"""The one NeRF trainer: what fits and joint training share, and the ray bank it draws from."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from csa_core.adapt.nerf_training import NerfLabelTrainer
from csa_core.data.scene import Frame
from csa_core.nerf.config import LossConfig
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.rays import RayBank, image_rays
from csa_core.nerf.samplers import DepthGuidedSampler, OccupancySampler, ReferenceSampler
from csa_core.nerf.trainer import NerfTrainer
from tests.nerf.conftest import synthetic_scene, tiny_config


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(frames=6, size=(24, 16))


@pytest.fixture
def nerf(scene):
    return fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=20), progress=False)[0]


def test_ray_bank_rays_are_the_image_rays_of_their_frame(scene):
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    hw = scene.intrinsics.width * scene.intrinsics.height
    assert bank.count == len(scene.train_frames) * hw and bank.has_depth
    ids = torch.tensor([0, 5, hw + 7, 3 * hw - 1])
    origins, dirs, target = bank.batch(ids)
    for k, i in enumerate(ids.tolist()):
        f = scene.train_frames[i // hw]
        o, d = image_rays(scene.intrinsics, f.pose)
        torch.testing.assert_close(origins[k], o[i % hw])
        torch.testing.assert_close(dirs[k], d[i % hw])
        assert int(target["frame"][k]) == i // hw
        assert int(target["labels"][k]) == int(f.labels["label-nyu40"].reshape(-1)[i % hw])
        assert float(target["depth"][k]) == pytest.approx(float(f.depth.reshape(-1)[i % hw]))
    with pytest.raises(KeyError, match=scene.train_frames[0].name):
        bank.set_labels({})


def test_ray_bank_marks_the_pixels_beside_a_nearer_surface(scene):
    """A pole 1 m in front of a wall 3 m away: the wall's pixels next to the pole (and only
    they) border a nearer surface; the pole's own pixels, pixels without depth and a hole next
    to the pole do not count."""
    intr = scene.intrinsics
    h, w = intr.height, intr.width
    depth = np.full((h, w), 3.0, np.float32)
    depth[:, 10] = 2.0  # the pole
    depth[5, 3] = 0.0  # a hole in the wall, far from the pole
    depth[7, 11] = 0.0  # a hole beside the pole
    f = scene.train_frames[0]
    frames = [
        Frame("0", f.color, f.pose, depth),
        Frame("1", f.color, f.pose, np.full_like(depth, 3)),
    ]
    bank = RayBank(frames, intr)
    beside = bank.beside_nearer_surface(lambda d: torch.full_like(d, 0.1)).view(2, h, w).numpy()
    expected = np.zeros((h, w), bool)
    expected[:, [9, 11]] = True
    expected[7, 11] = False
    assert (beside[0] == expected).all() and not beside[1].any()
    # A band wider than the pole's 1 m lead: nothing is beside a nearer surface.
    assert not bank.beside_nearer_surface(lambda d: torch.full_like(d, 1.5)).any()
    assert not bank.beside_nearer_surface(lambda d: 0.1 + 0.5 * d).any()  # 0.1 + 0.5 * 3 m


def test_free_space_edge_weighs_the_term_on_rays_beside_a_nearer_surface(scene):
    """``loss.free_space_edge`` scales the free-space term of the rays beside a nearer surface
    and of no other ray: 0 leaves them out, 1 is the plain term."""
    nerf = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=20), progress=False)[0]
    bank = RayBank(scene.train_frames, scene.intrinsics)
    beside = bank.beside_nearer_surface(nerf.config.sampler.band_half_width)
    assert beside.any() and not beside.all()
    ids = torch.cat([torch.nonzero(beside)[:64, 0], torch.nonzero(~beside)[:64, 0]])
    origins, dirs, target = bank.batch(ids)
    samples = nerf.sample(origins, dirs, nerf.train_sampler(has_depth=True), depth=target["depth"])
    out = nerf.render_samples(origins, dirs, samples, semantics=False)

    def free_space(edge_weight: float | None) -> float:
        t = dict(target)
        if edge_weight is not None:
            t["free_space_weight"] = torch.where(beside[ids], edge_weight, 1.0)
        return float(nerf.losses(out, t, samples)["free_space"].detach())

    plain, none_beside, half = free_space(None), free_space(0.0), free_space(0.5)
    only_beside = plain - none_beside
    assert plain > 0 and only_beside > 0  # the field puts weight in front beside edges
    assert half == pytest.approx(plain - 0.5 * only_beside, rel=1e-5)
    assert none_beside < plain
    with pytest.raises(ValueError, match="loss.free_space_edge"):
        LossConfig(free_space_edge=1.5)


def test_trainer_passes_the_edge_weight_only_when_it_is_below_one(scene):
    cfg = tiny_config(steps=2)
    cfg.loss.free_space_edge = 0.0
    nerf = fit_semantic_nerf(scene, "label-nyu40", cfg, progress=False)[0]
    bank = RayBank(scene.train_frames, scene.intrinsics)
    trainer = NerfTrainer(nerf, bank, schedule_steps=2)
    seen: list[dict] = []
    original = nerf.losses
    nerf.losses = lambda out, target, samples, scale=1.0: (  # type: ignore[method-assign]
        seen.append(target) or original(out, target, samples, scale)
    )
    trainer.train(1)
    assert "free_space_weight" in seen[-1]
    w = seen[-1]["free_space_weight"]
    assert set(w.unique().tolist()) <= {0.0, 1.0}
    nerf.config.loss.free_space_edge = 1.0
    trainer.train(1)
    assert "free_space_weight" not in seen[-1]


def test_the_model_owns_its_parameter_groups_and_the_optimiser_uses_them(nerf, scene):
    groups = nerf.parameter_groups()
    tables = {id(p) for p in groups[0]["params"]}
    assert id(nerf.field.encoding.table) in tables and id(nerf.field.semantic_table) in tables
    assert groups[0]["weight_decay"] == 0.0
    assert groups[1]["weight_decay"] == nerf.config.optim.weight_decay_mlp > 0
    every = {id(p) for p in nerf.parameters()}
    assert tables | {id(p) for p in groups[1]["params"]} == every
    label = NerfLabelTrainer(nerf, scene)
    decays = [g["weight_decay"] for g in label.trainer.optimizer.param_groups]
    assert decays == [0.0, nerf.config.optim.weight_decay_mlp]


def test_fit_and_joint_training_share_the_loop_with_the_free_space_term(nerf, scene):
    """Joint training's NeRF steps use the fit's losses, free-space term included."""
    assert nerf.config.loss.free_space > 0
    trainer = NerfLabelTrainer(nerf, scene, rays_per_step=128)
    trainer.set_labels({f.name: f.labels["label-nyu40"] for f in scene.train_frames})
    terms = trainer.train(3)
    assert {"color", "depth", "semantic", "free_space", "loss"} <= set(terms)
    assert trainer.steps_done == 3
    expected = sum(
        w * terms[k]
        for k, w in [("color", 1.0), ("depth", 0.1), ("semantic", 0.04), ("free_space", 1.0)]
    )
    assert terms["loss"] == pytest.approx(expected, rel=1e-5)
    # Constant rate in joint training: the fit's final one (a tenth of its start in `fast`).
    lr = [g["lr"] for g in trainer.trainer.optimizer.param_groups]
    assert lr == pytest.approx([nerf.config.optim.lr * nerf.config.optim.final_lr_fraction] * 2)


def test_fit_learning_rate_decays_to_its_final_fraction(scene):
    cfg = tiny_config(steps=10)
    nerf = fit_semantic_nerf(scene, "label-nyu40", cfg, progress=False)[0]
    trainer = NerfTrainer(nerf, RayBank(scene.train_frames, scene.intrinsics), schedule_steps=10)
    trainer.train(10)
    lr = trainer.optimizer.param_groups[0]["lr"]
    assert lr == pytest.approx(cfg.optim.lr * cfg.optim.final_lr_fraction, rel=1e-6)


def test_free_space_ramps_in_after_the_warm_up(nerf, scene):
    trainer = NerfTrainer(
        nerf, RayBank(scene.train_frames, scene.intrinsics), schedule_steps=10, free_space_warmup=4
    )
    scales = []
    for _ in range(10):
        scales.append(trainer.free_space_scale())
        trainer.steps_done += 1
    assert scales == pytest.approx([0, 0, 0, 0, 0, 0.25, 0.5, 0.75, 1, 1])


def test_semantic_steps_move_only_the_semantic_head(nerf, scene):
    before = {n: p.detach().clone() for n, p in nerf.named_parameters()}
    trainer = NerfLabelTrainer(nerf, scene, rays_per_step=128)
    trainer.set_labels({f.name: f.labels["label-nyu40"] for f in scene.train_frames})
    first = trainer.train_semantics(1)
    last = trainer.train_semantics(30)
    assert last < first
    moved = {n for n, p in nerf.named_parameters() if not torch.equal(p, before[n])}
    assert moved and all(
        n.startswith(("field.semantic_table", "field.semantic_mlp")) for n in moved
    )


def test_semantic_steps_decay_their_rate_to_the_configured_fraction(nerf, scene, monkeypatch):
    """``optim.semantic_final_lr_fraction``: the semantic steps' rate falls exponentially from
    ``lr`` at the first step to ``lr * fraction`` at the last; 1.0 holds it constant."""
    import csa_core.nerf.trainer as trainer_module

    rates: list[float] = []
    make = trainer_module.make_adam

    def recording_adam(groups, lr, owner):
        opt = make(groups, lr, owner)
        opt.register_step_pre_hook(lambda o, *_: rates.append(o.param_groups[0]["lr"]))
        return opt

    monkeypatch.setattr(trainer_module, "make_adam", recording_adam)
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    for fraction in (0.05, 1.0):
        rates.clear()
        nerf.config.optim.semantic_final_lr_fraction = fraction
        NerfTrainer(nerf, bank, 5, seed=0).semantic_steps(5, lr=0.02, rays_per_step=64)
        assert rates[0] == pytest.approx(0.02) and rates[-1] == pytest.approx(0.02 * fraction)
        assert len(rates) == 5 and all(a >= b for a, b in zip(rates, rates[1:], strict=False))
    for bad in (0.0, 1.5, float("nan")):
        nerf.config.optim.semantic_final_lr_fraction = bad
        with pytest.raises(ValueError, match="semantic_final_lr_fraction"):
            NerfTrainer(nerf, bank, 5, seed=0).semantic_steps(1, rays_per_step=64)
    nerf.config.optim.semantic_final_lr_fraction = 1.0
    # The fit's schedule is made, and checked, the same way.
    with pytest.raises(ValueError, match="optim.final_lr_fraction must be in"):
        NerfTrainer(nerf, bank, 5, final_lr_fraction=0.0)


def test_trainer_is_deterministic_for_a_seed(scene):
    runs = []
    for _ in range(2):
        nerf = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=2), progress=False)[0]
        bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
        NerfTrainer(nerf, bank, schedule_steps=5, seed=3).train(5)
        runs.append(nerf.field.state_dict())
    for name, p in runs[0].items():
        assert torch.equal(p, runs[1][name]), name


def test_samplers_come_from_the_config_not_from_the_caller(scene):
    fast = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=2), progress=False)[0]
    assert isinstance(fast.train_sampler(has_depth=True), DepthGuidedSampler)
    assert isinstance(fast.train_sampler(has_depth=False), ReferenceSampler)
    guided = fast.render_sampler(with_depth=True)
    assert isinstance(guided, DepthGuidedSampler) and isinstance(guided.fallback, OccupancySampler)
    assert isinstance(fast.render_sampler(with_depth=False), OccupancySampler)
    reference = tiny_config(steps=2)
    reference.sampler.train, reference.sampler.render = "reference", "reference"
    reference.sampler.render_depth_guided = False
    ref = fit_semantic_nerf(scene, "label-nyu40", reference, progress=False)[0]
    assert isinstance(ref.render_sampler(with_depth=True), ReferenceSampler)
    with pytest.raises(ValueError, match="unknown sampler"):
        ref.make_sampler("sideways")


def test_label_trainer_without_labels_trains_colour_and_depth(nerf, scene):
    trainer = NerfLabelTrainer(nerf, scene, rays_per_step=64)
    assert trainer.labels is None
    terms = trainer.train(1)
    assert "semantic" not in terms and np.isfinite(terms["loss"])
    with pytest.raises(ValueError, match="set_labels"):
        trainer.train_semantics(1)


def test_a_fit_without_semantics_leaves_the_head_to_the_semantic_steps(scene):
    """``optim.semantics_in_fit=False``: the fit's steps ignore the labels (its geometry and
    colour are bit for bit those of a fit without labels) and the semantic head learns only
    in the semantic steps after the fit."""
    cfg = tiny_config(steps=15)
    cfg.optim.semantics_in_fit = False
    with pytest.raises(ValueError, match="semantic_steps"):
        fit_semantic_nerf(scene, "label-nyu40", cfg, progress=False)
    cfg.optim.semantic_steps, cfg.optim.semantic_rays_per_step = 30, 256
    with_labels = fit_semantic_nerf(scene, "label-nyu40", cfg, progress=False)[0]
    without = fit_semantic_nerf(scene, None, cfg, progress=False)[0]
    other = dict(without.named_parameters())
    semantic = set()
    for name, p in with_labels.named_parameters():
        if name.startswith("field.semantic_"):
            semantic.add(name)
        else:
            assert torch.equal(p, other[name]), name
    assert semantic and any(
        not torch.equal(p, other[n]) for n, p in with_labels.named_parameters() if n in semantic
    )
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    terms = NerfTrainer(without, bank, schedule_steps=2, semantics=False).train(2)
    assert "semantic" not in terms and "color" in terms


def test_the_budget_semantic_steps_run_inside_the_fit():
    """``NerfBudget.semantic_steps`` becomes the fit's ``optim.semantic_steps`` at the budget's
    ray batch: one place runs semantic steps (``fit_semantic_nerf``)."""
    from csa_core.adapt.config import NerfBudget
    from csa_core.adapt.pseudo_labels import nerf_config

    items = ("optim.rays_per_step=512", "optim.semantics_in_fit=false")
    cfg = nerf_config(NerfBudget(semantic_steps=25, overrides=items))
    assert cfg.optim.semantic_steps == 25 and cfg.optim.semantic_rays_per_step == 512
    assert cfg.optim.semantics_in_fit is False
    assert nerf_config(NerfBudget()).optim.semantics_in_fit is True  # the preset's own
    assert nerf_config(NerfBudget()).optim.semantic_steps == 0


def test_adaptation_budgets_draw_and_step_as_measured_not_as_the_fusion_preset():
    """``fast`` fuses labels with label-balanced draws and its own semantic steps from a tenth
    of the rate decaying to 5% of it, with Semantic-NeRF's loss; a budget built on it draws
    uniformly unless an item of its ``overrides`` sets ``optim.ray_batches``, runs its own
    semantic steps (none by default) at the fit's starting rate (``optim.lr``) held constant,
    keeps the paper's loss where its results were measured with it, and its ``overrides``
    still come last."""
    from csa_core.adapt.config import NerfBudget, cpu, paper, tiny
    from csa_core.adapt.pseudo_labels import nerf_config
    from csa_core.nerf.config import preset

    fast = preset("fast").optim
    assert fast.ray_batches == "class_balanced" and fast.semantic_steps == 300
    assert fast.semantic_rays_per_step == 8192 and fast.semantic_lr_fraction == 0.1
    assert fast.semantic_final_lr_fraction == 0.05
    assert preset("fast").loss.semantic_form == "semantic_nerf"
    for budget, draws, steps in (
        (cpu().nerf, "all", 0),
        (tiny().nerf, "all", 60),
        (paper().nerf, "per_view", 0),
    ):
        cfg = nerf_config(budget)
        o = cfg.optim
        assert (o.ray_batches, o.semantic_steps) == (draws, steps)
        assert o.semantic_ray_batches is None and o.semantic_lr_fraction == 1.0
        assert o.semantic_final_lr_fraction == 1.0 and cfg.loss.semantic_form == "paper"
    balanced = NerfBudget(overrides=("optim.ray_batches=class_balanced",), semantic_steps=5)
    o = nerf_config(balanced).optim
    assert (o.ray_batches, o.semantic_steps, o.semantic_rays_per_step) == (
        "class_balanced",
        5,
        1024,
    )
    later = NerfBudget(overrides=("optim.ray_batches=class_balanced", "optim.semantic_steps=7"))
    assert (nerf_config(later).optim.ray_batches, nerf_config(later).optim.semantic_steps) == (
        "class_balanced",
        7,
    )


def test_a_shortened_fit_keeps_its_share_of_semantic_steps(scene, monkeypatch):
    """``--steps`` (CLI) and ``fit_semantic_nerf(steps=...)`` scale the semantic-head steps
    after the fit with the fit's length, rounded up (``scaled_semantic_steps``)."""
    from csa_core.cli.main import build_parser
    from csa_core.cli.nerf import fit_config
    from csa_core.nerf.config import preset, scaled_semantic_steps

    fast = preset("fast").optim
    assert scaled_semantic_steps(fast, None) == 300 and scaled_semantic_steps(fast, 1500) == 300
    assert scaled_semantic_steps(fast, 150) == 30 and scaled_semantic_steps(fast, 1) == 1
    assert scaled_semantic_steps(fast, 0) == 0
    args = build_parser().parse_args(
        ["nerf", "fit", "S", "--out", "x.safetensors", "--steps", "150"]
    )
    assert (fit_config(args).optim.steps, fit_config(args).optim.semantic_steps) == (150, 30)
    ran = []
    monkeypatch.setattr(
        NerfTrainer, "semantic_steps", lambda self, n, **kw: ran.append((n, kw)) or 0.0
    )
    cfg = tiny_config(steps=100)
    cfg.optim.semantic_steps, cfg.optim.semantic_rays_per_step, cfg.optim.semantic_lr_fraction = (
        40,
        64,
        0.1,
    )
    fit_semantic_nerf(scene, "label-nyu40", cfg, steps=5, progress=False)
    assert len(ran) == 1 and ran[0][0] == 2
    assert (ran[0][1]["lr"], ran[0][1]["rays_per_step"]) == (pytest.approx(cfg.optim.lr * 0.1), 64)
    # The semantic steps report like the fit's steps (every 10 and the last): a cancel lands.
    monkeypatch.undo()
    heard: list[str] = []
    cfg.optim.semantic_steps = 300  # 300 * 5 / 100 = 15 after the 5 fit steps
    fit_semantic_nerf(
        scene, "label-nyu40", cfg, steps=5, progress=False, on_progress=lambda m, f: heard.append(m)
    )
    assert [m for m in heard if "semantic" in m] == [
        "NeRF semantic step 1/15",
        "NeRF semantic step 11/15",
        "NeRF semantic step 15/15",
    ]


def test_per_view_ray_batches_take_each_view_once_per_epoch(scene):
    """``optim.ray_batches="per_view"`` (the official code's batches): every step's rays come
    from one view, and an epoch (one step per view) visits every view once."""
    cfg = tiny_config(steps=0)
    cfg.optim.ray_batches = "per_view"
    nerf = fit_semantic_nerf(scene, None, cfg, progress=False)[0]
    bank = RayBank(scene.train_frames, scene.intrinsics)
    trainer = NerfTrainer(nerf, bank, schedule_steps=10, rays_per_step=64, seed=1)
    views = len(scene.train_frames)
    for _epoch in range(2):
        seen = []
        for _ in range(views):
            frames = (trainer.draw()[0] // bank.hw).unique().tolist()
            assert len(frames) == 1
            seen.append(frames[0])
        assert sorted(seen) == list(range(views))
    cfg.optim.ray_batches = "all"
    spread = NerfTrainer(nerf, bank, schedule_steps=10, rays_per_step=256).draw()[0] // bank.hw
    assert len(spread.unique()) > 1
    with pytest.raises(IndexError, match="frame"):
        bank.random_ids(4, frame=views)


def _label_bank(labels: np.ndarray) -> RayBank:
    """A bank of one 20x16 view of a scene (geometry irrelevant) with the given labels."""
    sc = synthetic_scene(frames=1, size=(20, 16))
    bank = RayBank(sc.train_frames[:1], sc.intrinsics)
    bank.set_labels({sc.train_frames[0].name: labels.reshape(16, 20)})
    return bank


def test_balanced_draws_favour_rare_labels_and_weigh_them_back():
    """``RayBank.balanced_ids``: a label on 0.9% of the pixels is drawn over 4x as often,
    no label less than half its share, every drawn pixel carries its label's ``p / q``, and
    the weighted label frequencies are the uniform ones (so every loss keeps its optimum)."""
    labels = np.full(320, 1, np.uint8)
    labels[:32] = 2  # 10% of the pixels
    labels[32:35] = 3  # about 1%
    bank = _label_bank(labels)
    gen = torch.Generator().manual_seed(0)
    ids, w = bank.balanced_ids(200_000, gen)
    drawn = bank.labels[ids].long()
    share = torch.bincount(drawn, minlength=4).double() / len(ids)
    assert share[3] > 0.035 and share[1] > 0.45  # rare: >3.5x its 0.9%; common: >= half
    truth = torch.tensor([0, 285, 32, 3], dtype=torch.float64) / 320
    expected_q = 0.5 * truth + 0.5 * truth.sqrt() / truth.sqrt().sum()
    torch.testing.assert_close(share, expected_q, atol=5e-3, rtol=0)
    for c in (1, 2, 3):
        torch.testing.assert_close(
            w[drawn == c], torch.full_like(w[drawn == c], float(truth[c] / expected_q[c]))
        )
    weighted = torch.bincount(drawn, weights=w.double(), minlength=4) / w.double().sum()
    torch.testing.assert_close(weighted, truth, atol=5e-3, rtol=0)
    assert set(ids.tolist()) == set(range(320))  # every pixel of every label can be drawn
    with pytest.raises(ValueError, match="labels"):
        RayBank(bank.frames, synthetic_scene(frames=1, size=(20, 16)).intrinsics).balanced_ids(4)


def test_weighted_losses_are_the_means_under_uniform_draws():
    """A batch with ``ray_weight``: each loss term is the weighted mean over its rays, and
    unit weights give the unweighted loss exactly."""
    from csa_core.nerf.losses import color_loss, depth_loss, semantic_loss

    gen = torch.Generator().manual_seed(3)
    pred, target = torch.rand(6, 3, generator=gen), torch.rand(6, 3, generator=gen)
    depth_pred = torch.rand(6, generator=gen)
    depth = torch.tensor([1.0, 0.0, 2.0, 1.5, 0.0, 0.7])
    probs = torch.softmax(torch.randn(6, 40, generator=gen), -1)
    labels = torch.tensor([1, 0, 5, 5, 40, 2])
    ones = torch.ones(6)
    assert color_loss(pred, target, ones) == pytest.approx(float(color_loss(pred, target)))
    assert depth_loss(depth_pred, depth, ones) == pytest.approx(
        float(depth_loss(depth_pred, depth))
    )
    assert semantic_loss(probs, labels, ones) == pytest.approx(float(semantic_loss(probs, labels)))
    # weight 2 on a ray counts it twice: the same as the batch with that ray repeated
    w = torch.tensor([2.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    rep = torch.tensor([0, 0, 1, 2, 3, 4, 5])
    assert color_loss(pred, target, w) == pytest.approx(float(color_loss(pred[rep], target[rep])))
    assert depth_loss(depth_pred, depth, w) == pytest.approx(
        float(depth_loss(depth_pred[rep], depth[rep]))
    )
    assert semantic_loss(probs, labels, w) == pytest.approx(
        float(semantic_loss(probs[rep], labels[rep]))
    )


def test_class_balanced_ray_batches_train_with_weights(scene):
    """``optim.ray_batches="class_balanced"``: the trainer draws label-stratified rays with
    their weights, and training fits the labels; a bank without labels draws uniformly."""
    cfg = tiny_config(steps=0)
    cfg.optim.ray_batches = "class_balanced"
    nerf = fit_semantic_nerf(scene, None, cfg, progress=False)[0]
    assert nerf.config.optim.ray_batches == "class_balanced"
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    trainer = NerfTrainer(nerf, bank, schedule_steps=30, rays_per_step=256, seed=2)
    ids, w = trainer.draw()
    assert w is not None and w.shape == ids.shape and bool((w > 0).all())
    first = trainer.step()["semantic"].item()
    last = trainer.train(30)["semantic"]  # (the total rises as the free-space term ramps in)
    assert last < 0.5 * first
    # The semantic-head steps (the fit's and the joint rounds') draw the same way.
    calls = []
    balanced_ids = bank.balanced_ids

    def spy(n, gen):
        calls.append(n)
        return balanced_ids(n, gen)

    bank.balanced_ids = spy
    loss = trainer.semantic_steps(4, rays_per_step=128)
    assert calls == [128] * 4 and math.isfinite(loss)
    plain = NerfTrainer(nerf, RayBank(scene.train_frames, scene.intrinsics), schedule_steps=1)
    assert plain.draw()[1] is None
    nerf.config.optim.ray_batches = "sometimes"
    with pytest.raises(ValueError, match="ray_batches"):
        NerfTrainer(nerf, bank, schedule_steps=1)


def test_semantic_steps_draw_their_own_way_with_semantic_ray_batches(scene):
    """``optim.semantic_ray_batches``: uniform fit steps with label-stratified semantic-head
    steps, and the other way round; None follows ``optim.ray_batches``."""
    cfg = tiny_config(steps=0)
    nerf = fit_semantic_nerf(scene, None, cfg, progress=False)[0]
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    calls: list[int] = []
    balanced_ids = bank.balanced_ids

    def spy(n, gen):
        calls.append(n)
        return balanced_ids(n, gen)

    bank.balanced_ids = spy
    for fit_draws, semantic_draws, fit_balanced, semantic_balanced in (
        ("all", "class_balanced", False, True),
        ("class_balanced", "all", True, False),
        ("all", None, False, False),
        ("class_balanced", None, True, True),
    ):
        nerf.config.optim.ray_batches = fit_draws
        nerf.config.optim.semantic_ray_batches = semantic_draws
        trainer = NerfTrainer(nerf, bank, schedule_steps=4, rays_per_step=64, seed=1)
        calls.clear()
        assert (trainer.draw()[1] is not None) == fit_balanced
        assert calls == ([64] if fit_balanced else [])
        calls.clear()
        assert math.isfinite(trainer.semantic_steps(3, rays_per_step=32))
        assert calls == ([32] * 3 if semantic_balanced else [])
    nerf.config.optim.semantic_ray_batches = "per_view"
    with pytest.raises(ValueError, match="semantic_ray_batches"):
        NerfTrainer(nerf, bank, schedule_steps=1)


def test_the_cpu_preset_fits_and_joint_trains_its_nerf_at_a_fixed_rate(scene):
    """`cpu` keeps the NeRF's rate fixed, as the paper does (the `fast` preset decays it):
    the fit ends at its starting rate and joint training's NeRF steps run at the same rate."""
    from csa_core.adapt.config import cpu
    from csa_core.adapt.pseudo_labels import nerf_config
    from csa_core.nerf.config import preset

    assert preset("fast").optim.final_lr_fraction < 1.0
    optim = nerf_config(cpu().nerf).optim
    assert optim.final_lr_fraction == 1.0
    cfg = tiny_config(steps=6)
    cfg.optim.final_lr_fraction = optim.final_lr_fraction
    nerf = fit_semantic_nerf(scene, "label-nyu40", cfg, progress=False)[0]
    fit = NerfTrainer(nerf, RayBank(scene.train_frames, scene.intrinsics), schedule_steps=6)
    fit.train(6)
    assert [g["lr"] for g in fit.optimizer.param_groups] == pytest.approx([optim.lr] * 2)
    joint = NerfLabelTrainer(nerf, scene, rays_per_step=64)
    assert [g["lr"] for g in joint.trainer.optimizer.param_groups] == pytest.approx([optim.lr] * 2)


def test_depth_weights_weigh_the_semantic_term_only(scene, monkeypatch):
    """``loss.semantic_depth_power``: a ray's semantic loss weighs (median depth / z)^p (z
    clamped at 0.3 m, rays without depth weigh 1); colour and depth stay unweighted, and both
    the fit's steps and the semantic-head steps use the weights."""
    from csa_core.nerf.config import LossConfig
    from csa_core.nerf.losses import color_loss, near_view_weight, semantic_loss, total_loss

    depth = torch.tensor([0.0, 0.1, 1.0, 2.0])
    torch.testing.assert_close(
        near_view_weight(depth, 2.0, 1.0), torch.tensor([1.0, 1 / 0.09, 1.0, 0.25])
    )
    gen = torch.Generator().manual_seed(1)
    out = {"rgb": torch.rand(4, 3, generator=gen), "depth": depth + 0.1}
    out["semantics"] = torch.softmax(torch.randn(4, 40, generator=gen), -1)
    batch = {
        "rgb": torch.rand(4, 3, generator=gen),
        "depth": depth,
        "labels": torch.tensor([1, 2, 3, 4]),
    }
    batch["semantic_weight"] = near_view_weight(depth, 2.0, 1.0)
    terms = total_loss(out, batch, LossConfig())
    assert terms["semantic"] == pytest.approx(
        float(semantic_loss(out["semantics"], batch["labels"], batch["semantic_weight"]))
    )
    assert terms["semantic"] != pytest.approx(
        float(semantic_loss(out["semantics"], batch["labels"]))
    )
    assert terms["color"] == pytest.approx(float(color_loss(out["rgb"], batch["rgb"])))

    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    ids = torch.arange(0, bank.count, 7)
    assert bank.near_weights(ids, 0.0) is None
    median = float(bank.depth[bank.depth > 0].median())
    torch.testing.assert_close(
        bank.near_weights(ids, 2.0), near_view_weight(bank.depth[ids], 2.0, median)
    )

    cfg = tiny_config(steps=0)
    cfg.loss.semantic_depth_power = 2.0
    nerf = fit_semantic_nerf(scene, None, cfg, progress=False)[0]
    trainer = NerfTrainer(nerf, bank, schedule_steps=2, rays_per_step=64, seed=0)
    seen = []
    losses = nerf.losses

    def spy_losses(out, target, samples, scale=1.0):
        seen.append(target.get("semantic_weight"))
        return losses(out, target, samples, scale)

    monkeypatch.setattr(nerf, "losses", spy_losses)
    trainer.step()
    assert seen[0] is not None and seen[0].shape == (64,)
    weights = []

    def spy_semantic(probs, labels, ray_weight=None):
        weights.append(ray_weight)
        return semantic_loss(probs, labels, ray_weight)

    monkeypatch.setattr("csa_core.nerf.trainer.semantic_loss", spy_semantic)
    trainer.semantic_steps(2, rays_per_step=32)
    assert len(weights) == 2 and all(w is not None and w.shape == (32,) for w in weights)
    # A negative power weighs far rays up: p = -2 gives each ray the area its pixel covers.
    torch.testing.assert_close(
        near_view_weight(depth, -2.0, 1.0), torch.tensor([1.0, 0.09, 1.0, 4.0])
    )
    nerf.config.loss.semantic_depth_power = -2.0
    far = NerfTrainer(nerf, bank, schedule_steps=1)
    near = bank.near_weights(ids, 2.0)
    torch.testing.assert_close(bank.near_weights(ids, -2.0), 1 / near)
    assert far.near_power == -2.0
    nerf.config.loss.semantic_depth_power = float("nan")
    with pytest.raises(ValueError, match="semantic_depth_power"):
        NerfTrainer(nerf, bank, schedule_steps=1)


def _surface_nll(nerf, bank) -> float:
    """NLL of the labels under the semantic head at every labelled pixel's measured surface."""
    ids = torch.nonzero((bank.depth > 0) & (bank.labels > 0)).squeeze(-1)
    origins, dirs = bank.rays(ids)
    with torch.no_grad():
        _, logits = nerf.field.semantics(nerf.box.to_unit(origins + dirs * bank.depth[ids, None]))
    return float(torch.nn.functional.cross_entropy(logits, bank.labels[ids].long() - 1))


def test_the_surface_term_fits_the_labels_at_the_measured_surface(scene):
    """``loss.semantic_surface``: the semantic-head steps also fit each ray's label at its
    measured surface point, so the head there agrees with the labels better than after the
    same steps without the term; rays without depth add nothing to it."""
    fitted = fit_semantic_nerf(scene, None, tiny_config(steps=20), progress=False)[0]
    state = {k: v.clone() for k, v in fitted.state_dict().items()}
    nll = {}
    for weight in (0.0, 1.0):
        fitted.load_state_dict(state)
        fitted.config.loss.semantic_surface = weight
        bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
        before = _surface_nll(fitted, bank)
        NerfTrainer(fitted, bank, schedule_steps=1, seed=3).semantic_steps(15, rays_per_step=256)
        nll[weight] = _surface_nll(fitted, bank)
        assert nll[weight] < before
    assert nll[1.0] < nll[0.0]
    # Without any measured depth the term is empty and the steps stay finite.
    fitted.load_state_dict(state)
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    bank.depth.zero_()
    trainer = NerfTrainer(fitted, bank, schedule_steps=1, seed=3)
    assert math.isfinite(trainer.semantic_steps(2, rays_per_step=64))


def test_the_faint_only_surface_term_weighs_each_ray_by_its_missing_opacity(scene):
    """``loss.semantic_surface_faint_only``: a ray whose samples are opaque adds nothing to the
    surface term, a ray without weight adds its full share, and the term is a mean over every
    ray (a few faint rays are not scaled up to the whole term)."""
    nerf = fit_semantic_nerf(scene, None, tiny_config(steps=5), progress=False)[0]
    bank = RayBank(scene.train_frames, scene.intrinsics, label_folder="label-nyu40")
    trainer = NerfTrainer(nerf, bank, schedule_steps=1, seed=0)
    ids = torch.nonzero((bank.depth > 0) & (bank.labels > 0)).squeeze(-1)[:64]
    origins, dirs = bank.rays(ids)
    labels = bank.labels[ids]
    weight = torch.linspace(0.5, 1.5, len(ids))

    def term(opacity):
        with torch.no_grad():
            return float(trainer._surface_term(ids, origins, dirs, labels, weight, opacity))

    # The semantic steps' forward pass gives the opacity only where the option reads it.
    samples = nerf.sample(origins, dirs, nerf.render_sampler(with_depth=True), bank.depth[ids])
    for faint_only in (False, True):
        nerf.config.loss.semantic_surface_faint_only = faint_only
        with torch.no_grad():
            opacity = nerf.render_semantics(origins, dirs, samples)[1]
        assert (opacity is not None) == faint_only
    assert opacity.shape == (len(ids),) and bool(((opacity >= 0) & (opacity <= 1 + 1e-5)).all())

    full = term(None)
    assert full > 0
    assert term(torch.zeros(len(ids))) == pytest.approx(full, rel=1e-5)
    assert term(torch.ones(len(ids))) == 0.0
    assert term(torch.full((len(ids),), 0.75)) == pytest.approx(0.25 * full, rel=1e-5)
    # Half the rays opaque: the term is the faint half's weighted sum over all rays' weight.
    half = torch.cat([torch.ones(32), torch.zeros(32)])
    with torch.no_grad():
        logits = nerf.surface_logits(origins, dirs, bank.depth[ids])
    ce = torch.nn.functional.cross_entropy(logits, labels.long() - 1, reduction="none")
    expected = float((ce * weight)[32:].sum() / weight.sum())
    assert term(half) == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError, match="semantic_surface_faint_only"):
        type(nerf.config.loss)(semantic_surface_faint_only="yes")
