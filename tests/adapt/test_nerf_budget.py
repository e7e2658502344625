"""The adaptation budget's NeRF config: a NeRF preset and ``NerfConfig`` items, built through
the one override path (``csa_core.adapt.config.nerf_config`` calls
``csa_core.nerf.config.build_config``).

Every adaptation preset's effective NeRF config is pinned field by field against its NeRF
preset: the values below are those the budget gave before it held its NeRF settings as items
(when they were fields of their own), so the items change nothing. The ``--set`` keys of those
fields still work and give what they gave."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from csa_core.adapt.config import PRESETS, NerfBudget, nerf_config, preset
from csa_core.adapt.finetune import step_nerf_budget
from csa_core.errors import CSAInputError
from csa_core.nerf.config import NerfConfig, build_config
from csa_core.nerf.config import preset as nerf_preset
from csa_core.overrides import apply_overrides

# Adaptation preset -> (its NeRF preset, every field of its effective NeRF config that differs
# from that preset's own), as the budget's former fields produced them.
PAPER_NERF = {
    "field.encoding.finest_resolution": 8192,
    "field.semantic_grid_levels": 0,
    "field.semantic_hidden_layers": 1,
    "normalization": "cube",
    "optim.final_lr_fraction": 1.0,
    "optim.ray_batches": "per_view",
    "optim.steps": 1500,
    "sampler.occupancy_resolution": 32,
}
EXPECTED: dict[str, tuple[str, dict[str, Any]]] = {
    "paper": ("reference", PAPER_NERF),
    "paper-official": ("reference", {**PAPER_NERF, "field.semantic_detach_geometry": False}),
    "cpu": (
        "fast",
        {
            "field.encoding.finest_resolution": 1024,
            "field.encoding.log2_table_size": 14,
            "field.semantic_grid_levels": 12,
            "loss.semantic_form": "paper",
            "loss.semantic_surface": 0.0,
            "optim.final_lr_fraction": 1.0,
            "optim.ray_batches": "all",
            "optim.semantic_final_lr_fraction": 1.0,
            "optim.semantic_lr_fraction": 1.0,
            "optim.semantic_rays_per_step": 1024,
            "optim.semantic_steps": 0,
            "optim.steps": 300,
            "observed_resolution": 0,
            "render_unseen_unknown": False,
            "sampler.render_band_label_behind": None,
            "sampler.render_surface_label_weight": 0.0,
        },
    ),
    "tiny": (
        "fast",
        {
            "field.encoding.finest_resolution": 128,
            "field.encoding.log2_table_size": 12,
            "field.encoding.num_levels": 6,
            "loss.semantic_form": "paper",
            "optim.ray_batches": "all",
            "optim.rays_per_step": 256,
            "optim.semantic_final_lr_fraction": 1.0,
            "optim.semantic_lr_fraction": 1.0,
            "optim.semantic_rays_per_step": 256,
            "optim.semantic_steps": 60,
            "optim.steps": 80,
            "sampler.occupancy_resolution": 32,
            "observed_resolution": 0,
            "render_unseen_unknown": False,
            "sampler.render_band_label_behind": None,
            "sampler.render_surface_label_weight": 0.0,
        },
    ),
}
# Fit steps before the pseudo-labels on a scene of 10 training views, by mode.
STEP_FITS = {
    "paper": {"gi_nl": 600, "ni_nl": 600, "joint": 100},
    "paper-official": {"gi_nl": 600, "ni_nl": 600, "joint": 100},
    "cpu": {"gi_nl": 300, "ni_nl": 300, "joint": 300},
    "tiny": {"gi_nl": 80, "ni_nl": 80, "joint": 80},
}


def flat(config: NerfConfig) -> dict[str, Any]:
    """``{dotted key: value}`` of every leaf field of a NeRF config."""

    def walk(d: dict[str, Any], prefix: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out |= walk(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v}
        return out

    return walk(config.to_dict(), "")


def assert_same(got: dict[str, Any], expected: dict[str, Any]) -> None:
    """Equal field by field, types included (``True`` is not ``1``, ``4.0`` not ``4``)."""
    assert got.keys() == expected.keys()
    differ = {
        k: (got[k], expected[k])
        for k in got
        if got[k] != expected[k] or type(got[k]) is not type(expected[k])
    }
    assert differ == {}


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_adaptation_preset_fits_the_nerf_config_it_always_had(name):
    assert set(EXPECTED) == set(PRESETS)  # a new preset gets its row here
    base, changes = EXPECTED[name]
    budget = preset(name).nerf
    assert budget.preset == base
    expected = flat(nerf_preset(base))
    assert set(changes) <= set(expected)
    assert_same(flat(nerf_config(budget)), expected | changes)
    scene = SimpleNamespace(train_frames=[None] * 10)
    for mode, steps in STEP_FITS[name].items():
        config = preset(name)
        config.mode = mode
        step = nerf_config(step_nerf_budget(config, scene))  # type: ignore[arg-type]
        assert_same(flat(step), expected | changes | {"optim.steps": steps})


def test_the_budget_is_built_by_the_one_override_path():
    """A budget's config is ``build_config`` of its preset with its schedule and items; the
    budget records the preset and the items, not a copy of NeRF fields."""
    budget = preset("cpu").nerf
    schedule = [
        "optim.steps=300",
        "optim.ray_batches=all",
        "optim.semantic_ray_batches=none",
        "optim.semantic_steps=0",
        "optim.semantic_lr_fraction=1.0",
        "optim.semantic_final_lr_fraction=1.0",
        "seed=0",
    ]
    built = build_config("fast", [*schedule, *budget.overrides])
    built.optim.semantic_rays_per_step = built.optim.rays_per_step
    assert nerf_config(budget) == built
    assert sorted(preset("cpu").to_dict()["nerf"]) == [
        "geometry_steps_per_round",
        "joint_prefit_epochs",
        "overrides",
        "prefit_epochs",
        "prefit_steps",
        "preset",
        "seed",
        "semantic_steps",
        "steps_per_round",
    ]
    # An item may set the semantic steps' rays itself; else they follow the fit's.
    own = NerfBudget(overrides=("optim.rays_per_step=512", "optim.semantic_rays_per_step=64"))
    assert (
        nerf_config(own).optim.rays_per_step,
        nerf_config(own).optim.semantic_rays_per_step,
    ) == (
        512,
        64,
    )
    with pytest.raises(CSAInputError, match="unknown NeRF preset 'huge'"):
        apply_overrides(preset("cpu"), ["nerf.preset=huge"])


def test_nerf_config_keys_add_items_and_the_old_keys_still_work():
    """``--set nerf.config.<NerfConfig key>=v`` adds an item; the keys of the budget's former
    NeRF fields add the same item (and do what those fields did); ``nerf.preset_overrides``
    adds its items after the preset's own."""
    new = apply_overrides(preset("cpu"), ["nerf.config.field.encoding.log2_table_size=16"])
    old = apply_overrides(preset("cpu"), ["nerf.log2_table_size=16"])
    assert new == old and new.nerf.overrides[-1] == "field.encoding.log2_table_size=16"
    assert nerf_config(new.nerf).field.encoding.log2_table_size == 16

    # The values the former fields gave (measured before they became items).
    rays = apply_overrides(preset("cpu"), ["nerf.rays_per_step=2048"])
    o = nerf_config(rays.nerf).optim
    assert (o.rays_per_step, o.semantic_rays_per_step) == (2048, 2048)
    fine = nerf_config(apply_overrides(preset("cpu"), ["nerf.finest_resolution=512"]).nerf)
    assert (fine.field.encoding.finest_resolution, fine.sampler.occupancy_resolution) == (512, 32)
    own = apply_overrides(preset("cpu"), ["nerf.rays_per_step=none", "nerf.preset=reference"])
    o = nerf_config(own.nerf).optim
    assert (o.rays_per_step, o.semantic_rays_per_step) == (4096, 4096)
    assert nerf_config(own.nerf).field.encoding.log2_table_size == 14  # cpu's, on reference
    unfine = nerf_config(apply_overrides(preset("tiny"), ["nerf.finest_resolution=none"]).nerf)
    assert (unfine.field.encoding.finest_resolution, unfine.sampler.occupancy_resolution) == (
        512,
        64,
    )
    items = [
        "nerf.semantic_grid_levels=0",
        "nerf.semantic_detach_geometry=false",
        "nerf.final_lr_fraction=0.1",
        "nerf.ray_batches=class_balanced",
        "nerf.num_levels=8",
        "nerf.semantic_hidden_layers=1",
        "nerf.seed=5",
    ]
    cfg = nerf_config(apply_overrides(preset("cpu"), items).nerf)
    assert (cfg.field.semantic_grid_levels, cfg.field.semantic_detach_geometry) == (0, False)
    assert (cfg.optim.final_lr_fraction, cfg.optim.ray_batches) == (0.1, "class_balanced")
    assert (cfg.field.encoding.num_levels, cfg.field.semantic_hidden_layers, cfg.seed) == (8, 1, 5)

    paper = apply_overrides(preset("paper"), ["nerf.preset_overrides=('loss.free_space=0.5',)"])
    assert paper.nerf.overrides == (*preset("paper").nerf.overrides, "loss.free_space=0.5")
    assert nerf_config(paper.nerf).normalization == "cube"  # the preset's items stay


def test_a_bad_nerf_key_names_the_item_and_the_nerf_config_field():
    with pytest.raises(CSAInputError) as err:
        apply_overrides(preset("cpu"), ["nerf.config.field.encoding.bogus=1"])
    assert err.value.where == "--set nerf.config.field.encoding.bogus=1"
    assert "section 'field.encoding' has no field 'bogus'" in err.value.problem
    with pytest.raises(CSAInputError) as err:
        apply_overrides(preset("cpu"), ["nerf.log2_table_size=big"])
    assert err.value.where == "--set nerf.log2_table_size=big"
    assert (
        "bad value for 'field.encoding.log2_table_size': expected an integer" in err.value.problem
    )
    with pytest.raises(CSAInputError, match=r"valid: preset, overrides, .*config.<NerfConfig key>"):
        apply_overrides(preset("cpu"), ["nerf.table_size=12"])
    with pytest.raises(CSAInputError, match="semantic_steps > 0"):
        apply_overrides(preset("cpu"), ["nerf.config.optim.semantics_in_fit=false"])


def test_csa_nerf_fit_builds_its_config_the_same_way():
    from csa_core.cli.main import build_parser
    from csa_core.cli.nerf import fit_config

    argv = ["nerf", "fit", "s", "--out", "n.safetensors", "--steps", "750", "--seed", "2"]
    args = build_parser().parse_args([*argv, "--set", "loss.free_space=0"])
    expected = build_config(
        "fast",
        ["optim.semantic_steps=150", "optim.steps=750", "seed=2", "loss.free_space=0"],
    )
    assert fit_config(args) == expected
