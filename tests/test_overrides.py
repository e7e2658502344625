"""``--set KEY=VALUE``: one override path for the adaptation and NeRF configs (csa_core.overrides),
and the commands that build their configs with it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Literal

import pytest

from csa_core.adapt.config import nerf_config
from csa_core.adapt.config import preset as adapt_preset
from csa_core.cli.main import build_parser, main
from csa_core.errors import CSAInputError
from csa_core.nerf.config import preset as nerf_preset
from csa_core.overrides import apply_overrides


@dataclass
class Inner:
    sizes: list[int] = field(default_factory=lambda: [1, 2])
    scales: tuple[float, ...] = (1.0,)
    limit: int | None = None
    name: str | None = "a"

    def __post_init__(self) -> None:
        if self.limit is not None and self.limit < 0:
            raise ValueError("Inner: limit must not be negative")


@dataclass
class Outer:
    inner: Inner = field(default_factory=Inner)
    kind: Literal["x", "y"] = "x"
    level: Literal[1, 2] = 1
    extra: Inner | None = field(default_factory=Inner)  # an optional section


def test_values_are_parsed_by_the_declared_type():
    config = adapt_preset("cpu")
    same = apply_overrides(
        config,
        [
            "collapse.enabled=off",
            "pool_batchnorm=No",
            "adabn=1",
            "replay.buffer_size=5",
            "seg.lr=3e-5",
            "nerf.prefit_epochs=2.5",
            "nerf.rays_per_step=none",
            "joint.schedule=batch",
            "adabn_placement=paper",
            "seg.device=cuda:1",
            "nerf.preset=reference",
        ],
    )
    assert same is config  # in place
    assert (config.collapse.enabled, config.pool_batchnorm, config.adabn) == (False, False, True)
    assert config.replay.buffer_size == 5 and isinstance(config.replay.buffer_size, int)
    assert config.seg.lr == 3e-5 and config.nerf.prefit_epochs == 2.5
    # nerf.rays_per_step (a field of earlier budgets) dropped cpu's item: the preset's own rays
    assert "optim.rays_per_step=1024" not in config.nerf.overrides
    reference = nerf_preset("reference").optim.rays_per_step
    assert nerf_config(config.nerf).optim.rays_per_step == reference
    assert (config.joint.schedule, config.adabn_placement) == ("batch", "paper")
    assert (config.seg.device, config.nerf.preset) == ("cuda:1", "reference")
    assert adapt_preset("cpu").collapse.enabled is True  # presets stay fresh

    nerf = apply_overrides(
        nerf_preset("fast"),
        ["optim.betas=(0.8, 0.9)", "field.encoding.log2_table_size=12", "sampler.train=occupancy"],
    )
    assert nerf.optim.betas == (0.8, 0.9) and isinstance(nerf.optim.betas, tuple)
    assert (nerf.field.encoding.log2_table_size, nerf.sampler.train) == (12, "occupancy")

    outer = apply_overrides(
        Outer(),
        [
            "inner.sizes=[3, 4, 5]",
            "inner.scales=(2, 0.5)",
            "inner.limit=7",
            "inner.name=null",
            "level=2",
        ],
    )
    assert outer.inner.sizes == [3, 4, 5] and outer.inner.scales == (2.0, 0.5)
    assert (outer.inner.limit, outer.inner.name, outer.level) == (7, None, 2)


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("joint.schedule=weekly", "expected one of round, batch, got 'weekly'"),
        ("collapse.fallback=retry", "expected one of predictions, skip"),
        ("replay.buffer_size=1.5", "expected an integer, got '1.5'"),
        ("collapse.enabled=maybe", "expected true or false"),
        ("nerf.prefit_epochs=soon", "expected a number or none"),
        ("seg.lr=", "expected a number"),
    ],
)
def test_a_bad_value_names_the_item_the_key_and_the_type(item, message):
    with pytest.raises(CSAInputError) as err:
        apply_overrides(adapt_preset("cpu"), [item])
    assert err.value.where == f"--set {item}"
    assert f"bad value for {item.partition('=')[0]!r}" in err.value.problem
    assert message in err.value.problem


def test_literals_tuples_and_lists_are_checked_item_by_item_and_never_evaluated():
    with pytest.raises(CSAInputError, match=r"expected 2 items like \(1,1\), got '\(1,\)'"):
        apply_overrides(nerf_preset("fast"), ["optim.betas=(1,)"])
    with pytest.raises(CSAInputError, match="expected a tuple literal"):
        apply_overrides(nerf_preset("fast"), ["optim.betas=__import__('os').getcwd()"])
    with pytest.raises(CSAInputError, match="expected a list literal"):
        apply_overrides(Outer(), ["inner.sizes=[1, 'two']"])
    with pytest.raises(CSAInputError, match="expected one of x, y"):
        apply_overrides(Outer(), ["kind=z"])
    with pytest.raises(CSAInputError, match="expected one of 1, 2, got '3'"):
        apply_overrides(Outer(), ["level=3"])
    # a str field takes the text as it is
    assert (
        apply_overrides(adapt_preset("cpu"), ["seg.schedule=__import__('os')"]).seg.schedule
        == "__import__('os')"
    )


def test_an_unknown_key_lists_the_valid_fields_at_its_level():
    with pytest.raises(CSAInputError) as err:
        apply_overrides(adapt_preset("cpu"), ["collapse.enabld=false"])
    assert err.value.where == "--set collapse.enabld=false"
    assert "unknown key 'collapse.enabld'" in err.value.problem
    assert "section 'collapse' has no field 'enabld'" in err.value.problem
    assert (
        "(valid: enabled, min_entropy_ratio, max_dominant_gain, min_kappa, fallback)"
        in err.value.problem
    )
    with pytest.raises(
        CSAInputError, match=r"AdaptConfig has no field 'modes' \(valid: mode, nerf, seg, joint"
    ):
        apply_overrides(adapt_preset("cpu"), ["modes=joint"])
    with pytest.raises(CSAInputError, match="'mode' is a field, not a section"):
        apply_overrides(adapt_preset("cpu"), ["mode.x=1"])
    with pytest.raises(
        CSAInputError,
        match="'joint' is a section and cannot be set whole; set its fields: joint.rounds",
    ):
        apply_overrides(adapt_preset("cpu"), ["joint=1"])
    with pytest.raises(CSAInputError, match="expected KEY=VALUE"):
        apply_overrides(adapt_preset("cpu"), ["collapse.enabled"])
    with pytest.raises(CSAInputError, match="has no field 'epochs'"):  # a property, not a field
        apply_overrides(adapt_preset("cpu"), ["joint.epochs=3"])


def test_an_optional_section_can_be_switched_off_but_not_set_whole():
    outer = apply_overrides(Outer(), ["extra.limit=2"])
    assert outer.extra.limit == 2
    assert apply_overrides(outer, ["extra=none"]).extra is None
    with pytest.raises(
        CSAInputError, match="'extra' is none \\(off\\) in this config: it has no fields to set"
    ):
        apply_overrides(outer, ["extra.limit=3"])
    with pytest.raises(CSAInputError, match="expected Inner or none, got '1'"):
        apply_overrides(outer, ["extra=1"])
    with pytest.raises(
        CSAInputError,
        match=(
            r"cannot be set whole \(only to none or default: extra=none\); "
            r"set its fields: extra.sizes"
        ),
    ):
        apply_overrides(Outer(), ["extra=1"])
    with pytest.raises(CSAInputError, match=r"switch it on first with extra=default"):
        apply_overrides(Outer(extra=None), ["extra.limit=3"])
    # ``default`` switches an optional section on with its class's defaults (or resets it).
    back = apply_overrides(Outer(extra=None), ["extra=default", "extra.limit=3"])
    assert back.extra == Inner(limit=3)
    assert apply_overrides(Outer(extra=Inner(limit=5)), ["extra=DEFAULT"]).extra == Inner()
    with pytest.raises(CSAInputError, match="cannot be set whole"):
        apply_overrides(Outer(), ["inner=default"])  # not optional: fields only


def test_post_init_validation_runs_again_on_the_whole_tree():
    with pytest.raises(CSAInputError) as err:
        apply_overrides(adapt_preset("cpu"), ["seg.lr=1e-4", "mode=bogus"])
    assert err.value.where == "--set seg.lr=1e-4 --set mode=bogus"
    assert (
        "invalid config: AdaptConfig: mode must be one of gi_nl, ni_nl, joint, got 'bogus'"
        in err.value.problem
    )
    with pytest.raises(CSAInputError, match="Inner: limit must not be negative"):
        apply_overrides(Outer(), ["inner.limit=-1"])
    assert apply_overrides(adapt_preset("cpu"), ["mode=gi_nl"]).mode == "gi_nl"


# ---- the commands --------------------------------------------------------------------------

SET = ["--set", "collapse.enabled=false", "--set", "replay.buffer_size=5"]


def test_csa_adapt_applies_set_after_the_preset_and_the_flags():
    from csa_core.cli.adapt import adapt_config

    argv = [
        "adapt",
        "s0",
        "--model",
        "m.safetensors",
        "--out",
        "o",
        "--preset",
        "tiny",
        "--adabn",
        "on",
        "--seed",
        "3",
    ]
    args = build_parser().parse_args([*argv, *SET, "--set", "adabn=off", "--set", "nerf.seed=9"])
    config = adapt_config(args)
    assert (config.preset, config.collapse.enabled, config.replay.buffer_size) == ("tiny", False, 5)
    assert config.adabn is False  # --set is the last word over --adabn
    assert (config.nerf.seed, config.seg.seed) == (9, 3)
    assert adapt_config(build_parser().parse_args(argv)).collapse.enabled is True


def test_a_bad_set_fails_before_anything_is_read_or_written(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(
        [
            "adapt",
            str(tmp_path / "none"),
            "--model",
            str(tmp_path / "m.safetensors"),
            "--out",
            str(out),
            "--set",
            "replay.bufer_size=5",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("csa: error: --set replay.bufer_size=5: unknown key 'replay.bufer_size'")
    assert "valid: buffer_size, views," in err
    assert not out.exists()


def _inputs(args, tmp_path: Path):
    """The experiment inputs the command would build, without a checkpoint or scenes."""
    from csa_core.experiments.inputs import ExperimentInputs

    return ExperimentInputs(
        model_path=args.model,
        model=None,
        card=SimpleNamespace(arch="a", weights_id="w", input_size=None),
        scenes=[],
        scene_paths=[],
        out=tmp_path,
        preset=args.preset,
        seeds=[0, 1],
        device=args.device,
        mode=getattr(args, "mode", None),
        adabn=getattr(args, "adabn", None),
        overrides=args.set,
    )


@pytest.mark.parametrize("name", ["pseudo-labels", "one-step", "multi-step", "footprint"])
def test_every_experiment_takes_set_for_every_run(name, tmp_path):
    argv = [
        "experiment",
        name,
        "--model",
        "m",
        "--scenes",
        "s",
        "--out",
        "o",
        "--preset",
        "tiny",
        *SET,
    ]
    inputs = _inputs(build_parser().parse_args(argv), tmp_path)
    for seed in inputs.seeds:
        config = inputs.config(seed)
        assert (config.collapse.enabled, config.replay.buffer_size, config.nerf.seed) == (
            False,
            5,
            seed,
        )
    assert inputs.describe()["overrides"] == ["collapse.enabled=false", "replay.buffer_size=5"]


def test_multi_step_adabn_variants_follow_set(tmp_path):
    base = ["experiment", "multi-step", "--model", "m", "--scenes", "s", "--out", "o"]
    off = _inputs(build_parser().parse_args([*base, "--set", "adabn=false"]), tmp_path)
    assert off.adabn_variants() == [False]
    assert off.config(0, adabn=off.adabn_variants()[0]).adabn is False
    on = _inputs(
        build_parser().parse_args([*base, "--adabn", "off", "--set", "adabn=on"]), tmp_path
    )
    assert on.adabn_variants() == [True]
    from csa_core.experiments.inputs import load_inputs

    with pytest.raises(
        CSAInputError, match="--adabn both runs every method with and without AdaBN"
    ):
        load_inputs(
            tmp_path / "m", [tmp_path / "s"], tmp_path / "o", adabn="both", overrides=["adabn=off"]
        )
    with pytest.raises(
        CSAInputError, match="unknown key 'replay.bufer_size'"
    ):  # before the checkpoint is read
        load_inputs(
            tmp_path / "m", [tmp_path / "s"], tmp_path / "o", overrides=["replay.bufer_size=5"]
        )


def test_demo_and_nerf_fit_take_set(tmp_path):
    from csa_core.cli.demo import demo_config
    from csa_core.cli.nerf import fit_config

    args = build_parser().parse_args(
        ["demo", "--seed", "4", "--set", "pool_batchnorm=false", "--set", "mode=gi_nl"]
    )
    config = demo_config(args, "cpu")
    assert (config.pool_batchnorm, config.mode, config.seg.seed, config.seg.device) == (
        False,
        "gi_nl",
        4,
        "cpu",
    )

    argv = ["nerf", "fit", "scene", "--out", "n.safetensors", "--steps", "50", "--dtype", "float32"]
    cfg = fit_config(
        build_parser().parse_args([*argv, "--set", "optim.steps=70", "--set", "loss.free_space=0"])
    )
    assert (cfg.optim.steps, cfg.storage_dtype, cfg.loss.free_space) == (70, "float32", 0.0)
    assert fit_config(build_parser().parse_args(argv)).optim.steps == 50


def test_nerf_preset_fields_are_reachable_from_the_adaptation_config():
    """``nerf.preset_overrides``: any field of the NeRF preset, applied last to the NeRF
    config each scene's fit uses; a bad item is refused when the config is overridden."""
    from csa_core.adapt.config import cpu
    from csa_core.adapt.pseudo_labels import nerf_config

    items = ["nerf.preset_overrides=('sampler.render_band_color=false', 'loss.free_space=0.5')"]
    config = apply_overrides(cpu(), items)
    nerf = nerf_config(config.nerf)
    assert nerf.sampler.render_band_color is False and nerf.loss.free_space == 0.5
    assert nerf_config(cpu().nerf).sampler.render_band_color is True  # the preset's own
    with pytest.raises(CSAInputError, match="sampler.bogus"):
        apply_overrides(cpu(), ["nerf.preset_overrides=('sampler.bogus=1',)"])


def test_a_semantic_head_trained_after_the_fit_needs_semantic_steps():
    """``nerf.semantics_in_fit=false`` is refused when the config is made, not at a scene's
    fit, unless the budget also gives semantic steps."""
    with pytest.raises(CSAInputError, match="semantic_steps > 0"):
        apply_overrides(adapt_preset("cpu"), ["nerf.semantics_in_fit=false"])
    config = apply_overrides(
        adapt_preset("cpu"), ["nerf.semantic_steps=400", "nerf.semantics_in_fit=false"]
    )
    semantics_in_fit = nerf_config(config.nerf).optim.semantics_in_fit
    assert (config.nerf.semantic_steps, semantics_in_fit) == (400, False)


def test_the_augmentation_is_set_field_by_field_and_checked():
    """``seg.augment`` is a section like any other: the official code's augmentation (the
    ``paper`` preset's) is four ``--set`` items away from ours (the ``tiny`` preset's, and
    ``cpu``'s until it dropped augmentation: benchmarks/results/continual.md "Deviations
    measured with the multi-step experiment, second set"), and a bad strength is refused with
    the item named."""
    from csa_core.seg.config import official_augment

    official = [
        "seg.augment.rotation_deg=10",
        f"seg.augment.crop_scale=({1 / 1.2**2},{1 / 1.2**2})",
        "seg.augment.crop_aspect_jitter=0",
        "seg.augment.hue=0.05",
    ]
    config = apply_overrides(adapt_preset("tiny"), official)
    assert config.seg.augment == official_augment() == adapt_preset("paper").seg.augment
    assert adapt_preset("tiny").seg.augment.rotation_deg == 5.0  # the preset itself is untouched
    assert apply_overrides(adapt_preset("tiny"), ["seg.augment=none"]).seg.augment is None
    assert adapt_preset("cpu").seg.augment is None  # cpu trains on unaugmented pairs
    with pytest.raises(CSAInputError, match="'seg.augment' is none"):
        apply_overrides(adapt_preset("cpu"), official)
    # cpu with ours (the earlier cpu) and with the official augmentation
    assert (
        apply_overrides(adapt_preset("cpu"), ["seg.augment=default"]).seg.augment
        == adapt_preset("tiny").seg.augment
    )
    assert (
        apply_overrides(adapt_preset("cpu"), ["seg.augment=default", *official]).seg.augment
        == official_augment()
    )
    for item, message in (
        ("seg.augment.hflip=1.5", "hflip is a probability"),
        ("seg.augment.crop_scale=(0.9,0.5)", "crop_scale must be"),
        ("seg.augment.hue=-0.1", "hue must be in"),
    ):
        with pytest.raises(CSAInputError, match=message) as err:
            apply_overrides(adapt_preset("tiny"), [item])
        assert err.value.where == f"--set {item}"
