"""Rendering views, novel viewpoints, written outputs and the ``csa nerf`` commands."""

from __future__ import annotations

import argparse
import copy
import math

import cv2
import numpy as np
import pytest

from csa_core.cli.nerf import add_nerf_commands
from csa_core.data.scene_io import read_scene, write_scene
from csa_core.errors import CSAInputError
from csa_core.nerf.render import (
    interpolate_pose,
    novel_view_poses,
    render_views,
    view_poses,
    write_rendered_views,
)
from tests.nerf.conftest import tiny_config


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_novel_pose_is_the_slerp_midpoint_and_mean_translation():
    a, b = np.eye(4), np.eye(4)
    a[:3, :3], b[:3, :3] = _rot_z(0.2), _rot_z(1.0)
    a[:3, 3], b[:3, 3] = [0, 0, 1], [2, 4, 1]
    mid = interpolate_pose(a, b)
    np.testing.assert_allclose(mid[:3, :3], _rot_z(0.6), atol=1e-12)
    np.testing.assert_allclose(mid[:3, 3], [1, 2, 1])
    np.testing.assert_allclose(mid[3], [0, 0, 0, 1])
    # Antipodal quaternion signs do not flip the result.
    c = b.copy()
    c[:3, :3] = _rot_z(1.0 + 2 * math.pi)
    np.testing.assert_allclose(interpolate_pose(a, c)[:3, :3], _rot_z(0.6), atol=1e-12)
    names = novel_view_poses(["0", "10", "20"], [a, b, a])
    assert [n for n, _ in names] == ["0_10", "10_20"]


def test_view_selection(tiny_nerf, tiny_scene):
    assert [n for n, _ in view_poses(tiny_nerf, "train")] == [
        f.name for f in tiny_scene.train_frames
    ]
    assert len(view_poses(tiny_nerf, "novel")) == len(tiny_scene.train_frames) - 1
    assert [n for n, _ in view_poses(tiny_nerf, "val", tiny_scene)] == [
        f.name for f in tiny_scene.val_frames
    ]
    with pytest.raises(CSAInputError, match="scene"):
        view_poses(tiny_nerf, "val")
    with pytest.raises(CSAInputError):
        view_poses(tiny_nerf, "sideways", tiny_scene)


def test_written_views_read_back_as_a_scene(tiny_nerf, tiny_scene, tmp_path):
    views = render_views(tiny_nerf, tiny_scene, "val")
    out = write_rendered_views(views, tmp_path / "render", tiny_scene.intrinsics)
    back = read_scene(out, labels=["label-nyu40"])
    assert [f.name for f in back.frames] == [v.name for v in views]
    for f, v in zip(back.frames, views, strict=True):
        assert np.array_equal(f.color, v.color)
        assert np.array_equal(f.labels["label-nyu40"], v.labels)
        np.testing.assert_allclose(f.depth, np.round(v.depth * 1000) / 1000, atol=1e-6)
        np.testing.assert_allclose(f.pose, v.pose)
    raw = cv2.imread(str(out / "depth" / f"{views[0].name}.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert (out / "preview" / f"{views[0].name}.jpg").is_file()
    with pytest.raises(CSAInputError, match="exists"):
        write_rendered_views(views, out, tiny_scene.intrinsics)


def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="csa")
    add_nerf_commands(parser.add_subparsers(dest="group", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_fit_render_info(tiny_scene, tmp_path, monkeypatch, capsys):
    scene_dir = write_scene(tiny_scene, tmp_path / "scene")
    # The CLI uses the named presets; make "fast" tiny for the test.
    small = tiny_config(steps=10)
    monkeypatch.setattr(
        "csa_core.nerf.config.PRESETS",
        {"fast": lambda: copy.deepcopy(small), "reference": lambda: copy.deepcopy(small)},
    )
    ckpt = tmp_path / "scene.safetensors"
    assert (
        _cli(
            [
                "nerf",
                "fit",
                str(scene_dir),
                "--labels",
                "label-nyu40",
                "--out",
                str(ckpt),
                "--quiet",
            ]
        )
        == 0
    )
    assert ckpt.is_file()
    with pytest.raises(CSAInputError, match="exists"):
        _cli(["nerf", "fit", str(scene_dir), "--out", str(ckpt), "--quiet"])
    out = tmp_path / "novel"
    assert (
        _cli(["nerf", "render", str(ckpt), "--views", "novel", "--out", str(out), "--quiet"]) == 0
    )
    names = sorted(p.stem for p in (out / "label-nyu40").iterdir())
    assert len(names) == tiny_scene.num_train - 1 and all("_" in n for n in names)
    # A render option can change for one render; the fitted model's fields cannot.
    out2 = tmp_path / "novel-estimated"
    render = ["nerf", "render", str(ckpt), "--views", "novel", "--quiet"]
    assert _cli([*render, "--out", str(out2), "--set", "sampler.render_novel_estimate=true"]) == 0
    assert sorted(p.stem for p in (out2 / "label-nyu40").iterdir()) == names
    with pytest.raises(CSAInputError, match="not a render option"):
        _cli([*render, "--out", str(tmp_path / "y"), "--set", "field.hidden_dim=8"])
    with pytest.raises(CSAInputError, match="render_novel_estimat"):
        _cli([*render, "--out", str(tmp_path / "y"), "--set", "sampler.render_novel_estimat=1"])
    assert not (tmp_path / "y").exists()
    assert (
        _cli(
            [
                "nerf",
                "render",
                str(ckpt),
                "--scene",
                str(scene_dir),
                "--views",
                "val",
                "--out",
                str(tmp_path / "val"),
                "--quiet",
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "val" / "color").iterdir())) == len(tiny_scene.val_frames)
    capsys.readouterr()
    assert _cli(["nerf", "info", str(ckpt)]) == 0
    assert '"scene"' in capsys.readouterr().out
    with pytest.raises(CSAInputError, match="needs the scene"):
        _cli(
            ["nerf", "render", str(ckpt), "--views", "all", "--out", str(tmp_path / "x"), "--quiet"]
        )


def test_cli_render_refuses_a_scene_the_checkpoint_was_not_fitted_to(
    tiny_nerf, tiny_scene, tmp_path
):
    """Rendering another scene's views with a checkpoint gives labels of the wrong room: an
    error naming the scene folder, before any render and without an output folder."""
    from csa_core.nerf.checkpoint import save_checkpoint
    from tests.nerf.conftest import synthetic_scene

    ckpt = tmp_path / "a.safetensors"
    save_checkpoint(tiny_nerf, ckpt)
    own = write_scene(tiny_scene, tmp_path / "own")
    other = write_scene(synthetic_scene(seed=1), tmp_path / "other")
    render = ["nerf", "render", str(ckpt), "--views", "val", "--quiet", "--no-previews"]
    with pytest.raises(CSAInputError, match=r"other: frame 0 has another pose than the checkpoint"):
        _cli([*render, "--scene", str(other), "--out", str(tmp_path / "x")])
    renamed = copy.deepcopy(tiny_scene)
    for f in renamed.frames:
        f.name = f"f{f.name}"
    renamed_dir = write_scene(renamed, tmp_path / "renamed")
    with pytest.raises(CSAInputError, match=r"renamed: none of its frames is one the checkpoint"):
        _cli([*render, "--scene", str(renamed_dir), "--out", str(tmp_path / "x")])
    assert not (tmp_path / "x").exists()
    # An existing output is refused before the renders, and --every keeps the check passing.
    (tmp_path / "taken").mkdir()
    with pytest.raises(CSAInputError, match="taken: output already exists"):
        _cli([*render, "--scene", str(own), "--out", str(tmp_path / "taken")])
    assert _cli([*render, "--scene", str(own), "--every", "2", "--out", str(tmp_path / "ok")]) == 0


def test_cli_fit_refuses_a_folder_as_the_checkpoint_before_fitting(tiny_scene, tmp_path):
    scene_dir = write_scene(tiny_scene, tmp_path / "scene")
    (tmp_path / "out").mkdir()
    argv = ["nerf", "fit", str(scene_dir), "--out", str(tmp_path / "out"), "--overwrite", "--quiet"]
    with pytest.raises(CSAInputError, match="out: is a folder"):
        _cli(argv)


def test_pruned_inference_agrees_with_the_full_composite(tiny_nerf, tiny_scene):
    """The renderer evaluates colour and semantics only where a sample carries weight; its
    output must match compositing every sample (the reference) within a small tolerance."""
    import torch

    from csa_core.nerf.rays import image_rays

    f = tiny_scene.train_frames[2]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(f.depth.reshape(-1))
    for sampler, d in [
        (tiny_nerf.make_sampler("depth"), depth),
        (tiny_nerf.render_sampler(with_depth=False), None),
    ]:
        with torch.inference_mode():
            samples = tiny_nerf.sample(origins, dirs, sampler, depth=d)
            full = tiny_nerf.render_samples(origins, dirs, samples)
            fast = tiny_nerf.render_samples_pruned(origins, dirs, samples)
        for key in ("depth", "opacity", "rgb", "semantics"):
            torch.testing.assert_close(fast[key], full[key], atol=5e-3, rtol=0)
        assert torch.equal(fast["semantics"].argmax(-1), full["semantics"].argmax(-1))


def test_views_rendered_together_equal_views_rendered_alone(tiny_nerf, tiny_scene):
    from csa_core.nerf.render import render_frames, render_image

    frames = tiny_scene.train_frames[:4]
    poses = [(f.name, f.pose) for f in frames]
    depths = [f.depth if i % 2 else None for i, f in enumerate(frames)]  # mixed batches
    together = render_frames(tiny_nerf, poses, tiny_scene.intrinsics, depths, rays_per_pass=4096)
    for (name, pose), depth, view in zip(poses, depths, together, strict=True):
        alone = render_image(tiny_nerf, pose, tiny_scene.intrinsics, name=name, depth=depth)
        assert view.name == name
        np.testing.assert_allclose(view.depth, alone.depth, atol=1e-5)
        assert np.array_equal(view.labels, alone.labels)
        assert np.abs(view.color.astype(int) - alone.color).max() <= 1


def test_labels_only_rendering_skips_colour_and_keeps_the_labels(tiny_nerf, tiny_scene):
    from csa_core.nerf.render import render_pseudo_labels

    labels = render_pseudo_labels(tiny_nerf, tiny_scene, "train")
    full = render_views(tiny_nerf, tiny_scene, "train")
    assert [v.name for v in full] == list(labels)
    for v in full:
        assert np.array_equal(labels[v.name], v.labels)


def test_the_preset_decides_whether_views_with_depth_render_depth_guided(tiny_scene):
    """Views with depth render in the depth band when the config says so (fast), with the
    config's own sampler otherwise (reference): never by the caller's choice."""
    from csa_core.adapt.pseudo_labels import render_at_frames
    from csa_core.nerf.fit import fit_semantic_nerf
    from csa_core.nerf.render import render_frames

    frames = tiny_scene.train_frames[:2]
    poses, depths = [(f.name, f.pose) for f in frames], [f.depth for f in frames]
    cfg = tiny_config(steps=30)
    nerf = fit_semantic_nerf(tiny_scene, "label-nyu40", cfg, progress=False)[0]
    calls = []
    real = nerf.sample

    def spy(origins, dirs, sampler, **kw):
        calls.append(type(sampler).__name__)
        return real(origins, dirs, sampler, **kw)

    nerf.sample = spy
    render_frames(nerf, poses, tiny_scene.intrinsics, depths, color=False)  # labels only
    assert set(calls) == {"DepthGuidedSampler"}
    calls.clear()
    render_at_frames(nerf, frames, tiny_scene.intrinsics)  # labels in the band, colour marched
    assert set(calls) == {"DepthGuidedSampler", "OccupancySampler"}
    calls.clear()
    nerf.config.sampler.render_depth_guided = False
    render_at_frames(nerf, frames, tiny_scene.intrinsics)
    assert set(calls) == {"OccupancySampler"}


def test_views_with_depth_take_colour_from_the_full_ray_and_labels_from_the_band(tiny_scene):
    """Regression: a partly fitted field has little opacity inside the depth band, so colour
    composited from band samples alone comes out dark (held-out PSNR fell from 13 to 6 dB).
    A view with depth renders colour and depth as without depth, labels in the band."""
    import torch

    from csa_core.nerf.fit import fit_semantic_nerf
    from csa_core.nerf.losses import psnr
    from csa_core.nerf.rays import image_rays
    from csa_core.nerf.render import render_frames, render_image

    cfg = tiny_config(steps=30)
    cfg.sampler.render_band_color = False  # the paper's way; the band's colour: the next test
    nerf = fit_semantic_nerf(tiny_scene, "label-nyu40", cfg, progress=False)[0]
    assert nerf.config.sampler.render_depth_guided
    f = tiny_scene.val_frames[0]
    with_depth = render_image(nerf, f.pose, tiny_scene.intrinsics, depth=f.depth)
    without = render_image(nerf, f.pose, tiny_scene.intrinsics)
    assert np.array_equal(with_depth.color, without.color)
    np.testing.assert_array_equal(with_depth.depth, without.depth)
    (band,) = render_frames(nerf, [(f.name, f.pose)], tiny_scene.intrinsics, [f.depth], color=False)
    assert np.array_equal(with_depth.labels, band.labels)
    np.testing.assert_array_equal(with_depth.confidence, band.confidence)

    # What band samples alone would have composited: a darker, worse image.
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(f.depth.reshape(-1))
    band_only = nerf.render_rays(
        origins, dirs, nerf.render_sampler(with_depth=True), depth, semantics=False
    )
    target = f.color.reshape(-1, 3).astype(np.float64) / 255.0
    band_psnr = psnr(float(np.mean((band_only["rgb"].clamp(0, 1).numpy() - target) ** 2)))
    rendered_psnr = psnr(float(np.mean((with_depth.color.reshape(-1, 3) / 255.0 - target) ** 2)))
    assert rendered_psnr > band_psnr + 3.0, (rendered_psnr, band_psnr)


def test_band_colour_is_normalised_and_falls_back_to_the_whole_ray_where_the_band_is_thin(
    tiny_scene,
):
    """``render_band_color`` (the fast preset): colour and depth of a view with depth come
    from the band divided by its opacity; rays whose band holds too little opacity march
    the whole ray. The image is about as good as the whole-ray render, labels are the same."""
    import torch

    from csa_core.nerf.fit import fit_semantic_nerf
    from csa_core.nerf.losses import psnr
    from csa_core.nerf.rays import image_rays
    from csa_core.nerf.render import render_image

    nerf = fit_semantic_nerf(tiny_scene, "label-nyu40", tiny_config(steps=200), progress=False)[0]
    s = nerf.config.sampler
    assert s.render_band_color and s.render_depth_guided
    f = tiny_scene.val_frames[0]
    band = render_image(nerf, f.pose, tiny_scene.intrinsics, depth=f.depth)
    s.render_band_color = False
    whole = render_image(nerf, f.pose, tiny_scene.intrinsics, depth=f.depth)
    s.render_band_color = True
    target = f.color.astype(np.float64) / 255.0
    band_psnr = psnr(float(np.mean((band.color / 255.0 - target) ** 2)))
    whole_psnr = psnr(float(np.mean((whole.color / 255.0 - target) ** 2)))
    assert band_psnr > whole_psnr - 1.0, (band_psnr, whole_psnr)
    assert np.array_equal(band.labels, whole.labels)

    # Which rays used the band: those whose band opacity reaches the threshold; the others
    # carry exactly the whole ray's colour.
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    raw = nerf.render_rays(
        origins,
        dirs,
        nerf.render_sampler(with_depth=True),
        torch.as_tensor(f.depth.reshape(-1)),
        semantics=False,
    )
    used = (raw["opacity"] >= s.render_band_min_opacity).numpy()
    assert 0.2 < used.mean(), used.mean()  # the band carries most rays of a fitted field
    h, w = f.depth.shape
    used = used.reshape(h, w)
    assert np.array_equal(band.color[~used], whole.color[~used])
    expected = (raw["rgb"] / raw["opacity"][:, None]).clamp(0, 1).numpy().reshape(h, w, 3)
    assert np.abs(band.color[used] / 255.0 - expected[used]).max() <= 1.0 / 255 + 1e-6


@pytest.mark.parametrize("form", ["paper", "semantic_nerf"])
def test_an_empty_occupancy_grid_renders_a_blank_view_instead_of_failing(
    tiny_nerf, tiny_scene, form
):
    """No occupied cell: no samples on rays without depth. The render is blank (no colour,
    depth or opacity, zero label confidence, with either semantic loss's distribution), views
    with depth still get band labels, and a semantic step on such rays is a finite no-op loss
    rather than an error."""
    import torch

    from csa_core.nerf.rays import RayBank
    from csa_core.nerf.render import render_frames, render_image
    from csa_core.nerf.trainer import NerfTrainer

    nerf = copy.deepcopy(tiny_nerf)
    nerf.config.loss.semantic_form = form
    nerf.grid.occupied.zero_()
    f = tiny_scene.val_frames[0]
    blank = render_image(nerf, f.pose, tiny_scene.intrinsics)
    assert blank.color.shape == f.color.shape and not blank.color.any()
    assert not blank.depth.any() and not blank.confidence.any()
    assert blank.labels.min() >= 1 and blank.labels.max() <= 40

    half = f.depth.copy()
    half[: half.shape[0] // 2] = 0  # the top half has no measurement: marched, finds nothing
    (view,) = render_frames(nerf, [(f.name, f.pose)], tiny_scene.intrinsics, [half], color=False)
    top, bottom = view.confidence[: half.shape[0] // 2], view.confidence[half.shape[0] // 2 :]
    assert not top.any() and bottom[half[half.shape[0] // 2 :] > 0].min() > 0

    frames = copy.deepcopy(tiny_scene.train_frames[:2])
    for fr in frames:
        fr.depth = None
    rays = RayBank(frames, tiny_scene.intrinsics, label_folder="label-nyu40")
    trainer = NerfTrainer(nerf, rays, schedule_steps=1)
    samples = nerf.sample(*rays.rays(torch.arange(64)), nerf.render_sampler(with_depth=False))
    assert len(samples) == 0
    assert np.isfinite(trainer.semantic_steps(2, rays_per_step=64))


def test_the_march_keeps_the_features_the_render_would_compute_again(tiny_nerf, tiny_scene):
    """A novel view's march returns each kept sample's field features; rendering from them
    gives what evaluating the field again at those samples gives (the same samples: the
    features change nothing but the work)."""
    import torch

    from csa_core.nerf.rays import image_rays
    from csa_core.nerf.rendering import RaySamples

    f = tiny_scene.val_frames[0]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    sampler = tiny_nerf.render_sampler(with_depth=False)
    with torch.inference_mode():
        kept = tiny_nerf.sample(
            origins, dirs, sampler, density_fn=tiny_nerf._march_features(semantics=True)
        )
        plain = tiny_nerf.sample(origins, dirs, sampler)
        assert len(kept) > 0 and kept.features is not None and plain.features is None
        assert torch.equal(kept.ray_indices, plain.ray_indices)
        assert torch.equal(kept.t_starts, plain.t_starts)
        # The features are the field's at each kept sample, in the samples' order.
        pts = origins[kept.ray_indices] + dirs[kept.ray_indices] * kept.t_mids[:, None]
        sigma, geo, sem = tiny_nerf.field.features(tiny_nerf.box.to_unit(pts), True)
        # (t_mids rebuilt from the intervals and another batch: float noise only)
        torch.testing.assert_close(
            kept.features, torch.cat([sigma[:, None], geo, sem], -1), atol=1e-4, rtol=1e-4
        )
        again = RaySamples(kept.ray_indices, kept.t_starts, kept.t_ends, kept.num_rays)
        reused = tiny_nerf.render_samples_pruned(origins, dirs, kept)
        evaluated = tiny_nerf.render_samples_pruned(origins, dirs, again)
    for key in ("depth", "opacity", "rgb", "semantics"):
        torch.testing.assert_close(reused[key], evaluated[key], atol=1e-5, rtol=1e-5)
    # render_rays takes that path for a view without depth, and colour without semantics too.
    out = tiny_nerf.render_rays(origins, dirs)
    torch.testing.assert_close(out["semantics"], reused["semantics"], atol=1e-5, rtol=1e-5)
    colour_only = tiny_nerf.render_rays(origins, dirs, semantics=False)
    torch.testing.assert_close(colour_only["rgb"], reused["rgb"], atol=1e-5, rtol=1e-5)


def test_the_render_march_has_its_own_step_and_pruning(tiny_nerf):
    """``render_march_steps``, ``render_early_stop`` and ``render_min_weight`` shape the
    rendering march only; training marches keep the grid's step and are not pruned."""
    s = copy.deepcopy(tiny_nerf.config.sampler)
    try:
        cfg = tiny_nerf.config.sampler
        cfg.render_march_steps, cfg.render_early_stop, cfg.render_min_weight = 64, 0.02, 0.003
        render = tiny_nerf.make_sampler("occupancy")
        train = tiny_nerf.make_sampler("occupancy", training=True)
        assert render.step == pytest.approx(tiny_nerf.box.diagonal / 64)
        assert (render.early_stop_eps, render.min_weight, render.prune) == (0.02, 0.003, True)
        assert train.step == pytest.approx(tiny_nerf.grid.step_size(tiny_nerf.box))
        assert not train.prune
        cfg.render_march_steps = None
        assert tiny_nerf.make_sampler("occupancy").step == pytest.approx(train.step)
        cfg.render_march_steps = 0
        with pytest.raises(ValueError, match="render_march_steps"):
            tiny_nerf.make_sampler("occupancy")
        cfg.render_march_steps, cfg.render_early_stop = 64, 1.5
        with pytest.raises(ValueError, match="early_stop_eps"):
            tiny_nerf.make_sampler("occupancy")
    finally:
        tiny_nerf.config.sampler = s
    # Through the one override path (csa nerf render --set): an error naming the field.
    from csa_core.overrides import apply_overrides

    for item, field in [
        ("sampler.render_march_steps=0", "render_march_steps"),
        ("sampler.render_early_stop=1", "render_early_stop"),
        ("sampler.render_min_weight=-0.1", "render_min_weight"),
    ]:
        with pytest.raises(CSAInputError, match=field):
            apply_overrides(tiny_config(), [item])
    unset = apply_overrides(tiny_config(), ["sampler.render_march_steps=none"])
    assert unset.sampler.render_march_steps is None
