"""Kinect-like captures of clean scenes: depth noise, holes, label errors, determinism, errors."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.cli.main import main
from csa_core.data.camera import Intrinsics, backproject, project
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.data.scene_io import read_scene, write_scene
from csa_core.data.synth import (
    NOISY_FOLDER,
    KinectConfig,
    axial_sigma,
    degrade_scene,
    degrade_scene_folder,
    generate_scene,
    mix_depth_edges,
)
from csa_core.errors import CSAInputError
from tests.tiny_scenes import look_at_pose

# Only the effect under test: no lateral jitter, no colour noise, no label errors, no holes
# on dark or grazing surfaces.
QUIET = dict(
    lateral_px=0.0,
    dark_share=0.0,
    grazing_share=0.0,
    color_noise=0.0,
    systematic_share=0.0,
    frame_noise=None,
)


def camera(w: int = 160, h: int = 120, f: float = 120.0) -> Intrinsics:
    return Intrinsics(fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)


def scene_of(intr: Intrinsics, depths, colors=None, labels=None, poses=None) -> Scene:
    """A scene whose frames have the given depth maps (and grey colour, class-1 labels,
    identity poses unless given)."""
    frames = []
    for i, depth in enumerate(depths):
        color = colors[i] if colors is not None else np.full((*depth.shape, 3), 128, np.uint8)
        lab = labels[i] if labels is not None else np.ones(depth.shape, np.uint8)
        pose = poses[i] if poses is not None else np.eye(4)
        frames.append(
            Frame(
                name=str(i),
                color=color,
                pose=pose,
                depth=depth.astype(np.float32),
                labels={NYU40_FOLDER: lab},
            )
        )
    return Scene("test", intr, frames)


def ray_xy(intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    return (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy


@pytest.mark.parametrize("z", [1.0, 3.0])
def test_depth_noise_follows_the_axial_model(z: float) -> None:
    intr = camera()
    clean = scene_of(intr, [np.full((intr.height, intr.width), z)] * 4)
    noisy = degrade_scene(clean, seed=1)  # the default config, lateral jitter included
    err = np.concatenate([(f.depth - z).ravel() for f in noisy.frames]).astype(np.float64)
    assert all((f.depth > 0).all() for f in noisy.frames)  # a flat lit wall in range: no holes
    sigma = axial_sigma(z)
    assert sigma == pytest.approx(0.0012 + 0.0019 * (z - 0.4) ** 2)
    # 76,800 samples: the std estimate is good to about 0.3%, the mean to 3 sigma / sqrt(n).
    assert err.std() == pytest.approx(sigma, rel=0.03)
    assert abs(err.mean()) < 3 * sigma / np.sqrt(err.size)


def test_holes_at_depth_discontinuities_and_in_the_projector_shadow() -> None:
    intr = camera()
    depth = np.full((intr.height, intr.width), 3.0)
    depth[40:80, 60:100] = 1.5  # a box in front of a wall
    out = degrade_scene(scene_of(intr, [depth]), config=KinectConfig(**QUIET)).frames[0].depth
    holes = out == 0
    row = 60
    # Both sides of every jump are missing.
    assert holes[row, 59] and holes[row, 60] and holes[row, 99] and holes[row, 100]
    assert holes[39, 80] and holes[40, 80] and holes[79, 80] and holes[80, 80]
    # The projector, to the camera's right, cannot light the wall just left of the box:
    # a shadow of fx * baseline * (1/1.5 - 1/3) = 3 px minus the last column (strict test).
    left = np.flatnonzero(holes[row, :60])
    right = np.flatnonzero(holes[row, 100:])
    assert left.tolist() == [58, 59] and right.tolist() == [0]
    # Far from the box's outline nothing is missing.
    near = np.zeros_like(holes)
    near[36:84, 54:104] = True
    near[44:76, 64:96] = False
    assert not holes[~near].any()


def test_flying_pixels_lie_between_the_two_surfaces_of_a_jump() -> None:
    depth = np.full((60, 80), 3.0, np.float32)
    depth[20:40, 30:50] = 1.5  # a box in front of a wall
    depth[0, 0] = 0.0  # not measured: stays so
    share = 0.5
    out = mix_depth_edges(depth, np.random.default_rng(0), share)
    changed = out != depth
    # Only pixels on either side of the box's outline move, about ``share`` of them, and each
    # to between 10% and 90% of the way from the box to the wall.
    outline = np.zeros_like(changed)
    outline[19:41, 29:51] = True
    outline[21:39, 31:49] = False
    assert not changed[~outline].any()
    edge_pixels = outline.sum() - 4  # the four corners touch the box only diagonally
    assert 0.35 < changed.sum() / edge_pixels < 0.65
    assert np.all(
        (out[changed] >= 1.5 + 0.1 * 1.5 - 1e-6) & (out[changed] <= 1.5 + 0.9 * 1.5 + 1e-6)
    )
    assert out[0, 0] == 0.0 and out.dtype == np.float32
    # Deterministic for a seed; share 0 changes nothing; a share outside [0, 1] is refused.
    assert np.array_equal(out, mix_depth_edges(depth, np.random.default_rng(0), share))
    assert np.array_equal(mix_depth_edges(depth, np.random.default_rng(1), 0.0), depth)
    with pytest.raises(ValueError, match="share"):
        mix_depth_edges(depth, np.random.default_rng(0), 1.5)


def test_holes_on_dark_surfaces_come_in_patches_of_a_share() -> None:
    intr = camera()
    depth = np.full((intr.height, intr.width), 2.0)
    color = np.full((intr.height, intr.width, 3), 200, np.uint8)
    color[:, :80] = 20  # the left half is dark
    scene = scene_of(intr, [depth], colors=[color])
    cfg = {**QUIET, "dark_share": 1.0}
    holes = degrade_scene(scene, config=KinectConfig(**cfg)).frames[0].depth == 0
    assert holes[:, :80].all() and not holes[:, 80:].any()
    cfg["dark_share"] = 0.5
    holes = degrade_scene(scene, config=KinectConfig(**cfg)).frames[0].depth == 0
    assert not holes[:, 80:].any()
    assert 0.2 < holes[:, :80].mean() < 0.8
    # Patches: most missing pixels have missing neighbours on both sides.
    inner = holes[1:-1, 1:79]
    assert (inner & holes[1:-1, :78] & holes[1:-1, 2:80]).sum() > 0.8 * inner.sum()


def test_holes_on_grazing_surfaces() -> None:
    intr = camera()
    x, y = ray_xy(intr)
    # A floor 0.5 m below a camera looking level: z = 0.5 / y below the horizon.
    with np.errstate(divide="ignore"):
        depth = np.where(y > 0, 0.5 / y, 0.0)
    angle = np.degrees(np.arccos(np.abs(y) / np.sqrt(x**2 + y**2 + 1.0)))
    in_range = (depth > 0) & (depth < 5.0)
    grazing = in_range & (angle > 75.0)
    # No discontinuity test here (the far floor changes depth fast from row to row).
    cfg = {**QUIET, "edge_jump": 100.0, "grazing_share": 1.0}
    scene = scene_of(intr, [depth])
    holes = degrade_scene(scene, config=KinectConfig(**cfg)).frames[0].depth == 0
    # The estimated normal is exact on a plane, but its angle is tested at the clean depth
    # rounded to float32: allow the one-pixel rows at 75 degrees.
    near_75 = in_range & (np.abs(angle - 75.0) < 0.5)
    assert (holes == grazing)[in_range & ~near_75].all()
    assert grazing.sum() > 500 and (in_range & ~grazing).sum() > 500
    cfg["grazing_share"] = 0.5
    holes = degrade_scene(scene, config=KinectConfig(**cfg)).frames[0].depth == 0
    assert not holes[in_range & ~grazing & ~near_75].any()
    assert 0.2 < holes[grazing].mean() < 0.8


@pytest.fixture(scope="module")
def office() -> Scene:
    return generate_scene("office", 0, 12, (64, 48))


def same_points(scene: Scene, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (flat indices) of frames a and b that see the same surface point (clean depth)."""
    fa, fb = scene.frames[a], scene.frames[b]
    intr = scene.intrinsics
    pts = backproject(fa.depth, intr, fa.pose).reshape(-1, 3)
    uv, z = project(pts, intr, fb.pose)
    u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    ok = np.isfinite(z) & (z > 0) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    src = np.flatnonzero(ok)
    dst = (v[ok] * intr.width + u[ok]).astype(np.int64)
    same = np.abs(fb.depth.ravel()[dst] - z[ok]) < 0.01
    return src[same], dst[same]


def test_systematic_errors_are_the_same_in_every_view_from_one_side() -> None:
    """Two cameras 10 pixels' footprint apart in front of a wall see exactly the same points."""
    intr = camera(80, 60, 60.0)
    h, w = intr.height, intr.width
    labels = np.full((h, w), 5, np.uint8)
    labels[:, :4] = 7  # the scene needs a second class to be wrong with
    shift = np.eye(4)
    shift[0, 3] = 10 * 2.0 / intr.fx  # B's pixel u sees A's pixel u + 10
    scene = scene_of(
        intr, [np.full((h, w), 2.0)] * 2, labels=[labels] * 2, poses=[np.eye(4), shift]
    )
    cfg = KinectConfig(**{**QUIET, "systematic_share": 0.4, "region_size": 0.25})
    a, b = (f.labels[NOISY_FOLDER] for f in degrade_scene(scene, seed=1, config=cfg).frames)
    la, lb, gt = a[:, 14:], b[:, 4:-10], labels[:, 14:]
    mistaken = la != gt
    assert 0.1 < mistaken.mean() < 0.9
    np.testing.assert_array_equal(la, lb)


def test_systematic_errors_agree_across_a_room_walk(office: Scene) -> None:
    cfg = KinectConfig(systematic_share=0.3, frame_noise=None)
    noisy = degrade_scene(office, seed=0, config=cfg)
    wrong = [float((f.labels[NOISY_FOLDER] != f.labels[NYU40_FOLDER]).mean()) for f in noisy.frames]
    assert 0.05 < np.mean(wrong) < 0.6
    checked = 0
    for a, b in [(0, 2), (3, 5), (6, 9)]:
        src, dst = same_points(office, a, b)
        gt_a = office.frames[a].labels[NYU40_FOLDER].ravel()[src]
        gt_b = office.frames[b].labels[NYU40_FOLDER].ravel()[dst]
        keep = gt_a == gt_b  # the pixel centres fall on the same object in both views
        la = noisy.frames[a].labels[NOISY_FOLDER].ravel()[src][keep]
        lb = noisy.frames[b].labels[NOISY_FOLDER].ravel()[dst][keep]
        mistaken = la != gt_a[keep]
        checked += int(mistaken.sum())
        # Pixel centres of two views are up to a pixel apart (3-4 cm here), so a few pairs
        # straddle a region's border or a crease where the side changes.
        assert (la[mistaken] == lb[mistaken]).mean() > 0.9
        assert (la == lb).mean() > 0.94
    assert checked > 200


def test_the_other_side_of_a_surface_is_decided_apart() -> None:
    """A horizontal sheet seen from above (twice) and from below: errors agree between the two
    views from above and not with the view from below."""
    intr = camera(80, 60, 60.0)
    h, w = intr.height, intr.width
    labels = np.full((h, w), 5, np.uint8)
    labels[:, :8] = 7  # the scene needs a second class to be wrong with
    poses = [
        look_at_pose([0.0, 0.0, 2.0], [0.0, 0.001, 0.0]),
        look_at_pose([0.1, 0.0, 2.0], [0.1, 0.001, 0.0]),  # 3 pixels' footprint aside
        look_at_pose([0.0, 0.0, -2.0], [0.0, 0.001, 0.0]),
    ]
    # All three look straight at the sheet z = 0 from 2 m: depth 2 everywhere.
    scene = scene_of(intr, [np.full((h, w), 2.0)] * 3, labels=[labels] * 3, poses=poses)
    cfg = KinectConfig(**{**QUIET, "systematic_share": 0.5, "region_size": 0.25})
    noisy = degrade_scene(scene, seed=4, config=cfg)

    def agreement(a: int, b: int) -> float:
        src, dst = same_points(scene, a, b)
        la = noisy.frames[a].labels[NOISY_FOLDER].ravel()[src]
        lb = noisy.frames[b].labels[NOISY_FOLDER].ravel()[dst]
        keep = (labels.ravel()[src] == 5) & (labels.ravel()[dst] == 5)  # the same class
        assert keep.sum() > 1000
        return float((la[keep] == lb[keep]).mean())

    assert agreement(0, 1) > 0.99
    assert agreement(0, 2) < 0.8


def test_per_frame_errors_come_on_top_and_ground_truth_stays_clean(office: Scene) -> None:
    before = [f.labels[NYU40_FOLDER].copy() for f in office.frames]
    systematic = degrade_scene(office, seed=0, config=KinectConfig(frame_noise=None))
    full = degrade_scene(office, seed=0)
    for g, gt, orig in zip(full.frames, before, office.frames, strict=True):
        np.testing.assert_array_equal(g.labels[NYU40_FOLDER], gt)
        np.testing.assert_array_equal(orig.labels[NYU40_FOLDER], gt)  # input untouched
        assert NOISY_FOLDER not in orig.labels

    def accuracy(scene: Scene) -> float:
        pairs = zip(scene.frames, before, strict=True)
        return float(np.mean([(f.labels[NOISY_FOLDER] == gt).mean() for f, gt in pairs]))

    assert accuracy(full) < accuracy(systematic) - 0.1


def test_same_seed_same_capture_other_seed_other_capture(office: Scene) -> None:
    a = degrade_scene(office, seed=3)
    b = degrade_scene(office, seed=3)
    c = degrade_scene(office, seed=4)
    for fa, fb in zip(a.frames, b.frames, strict=True):
        np.testing.assert_array_equal(fa.depth, fb.depth)
        np.testing.assert_array_equal(fa.color, fb.color)
        np.testing.assert_array_equal(fa.labels[NOISY_FOLDER], fb.labels[NOISY_FOLDER])
    pairs = list(zip(a.frames, c.frames, strict=True))
    assert any(not np.array_equal(fa.depth, fc.depth) for fa, fc in pairs)
    assert any(
        not np.array_equal(fa.labels[NOISY_FOLDER], fc.labels[NOISY_FOLDER]) for fa, fc in pairs
    )
    # A frame's capture depends on its name and the seed, not on the other frames.
    alone = Scene(office.name, office.intrinsics, office.frames[5:6])
    one = degrade_scene(alone, seed=3, config=KinectConfig(systematic_share=0.0))
    many = degrade_scene(office, seed=3, config=KinectConfig(systematic_share=0.0))
    np.testing.assert_array_equal(one.frames[0].depth, many.frames[5].depth)
    np.testing.assert_array_equal(
        one.frames[0].labels[NOISY_FOLDER], many.frames[5].labels[NOISY_FOLDER]
    )


def test_bad_input_is_named(office: Scene, tmp_path) -> None:
    no_depth = Scene("flat", office.intrinsics, [Frame("0", office.frames[0].color, np.eye(4))])
    with pytest.raises(CSAInputError, match="needs depth; frame"):
        degrade_scene(no_depth)
    with pytest.raises(CSAInputError, match="no label folder 'label-x'"):
        degrade_scene(office, source="label-x")
    with pytest.raises(CSAInputError, match="--target"):
        degrade_scene(office, target=NYU40_FOLDER)
    small = Scene("small", camera(80, 60), office.frames[:1])  # 64x48 frames, 80x60 camera
    with pytest.raises(CSAInputError, match="frame 0: depth is 64x48, the scene's camera 80x60"):
        degrade_scene(small)
    with pytest.raises(CSAInputError, match="--seed"):
        degrade_scene(office, seed=-1)
    with pytest.raises(ValueError, match="dark_share"):
        KinectConfig(dark_share=1.5)
    with pytest.raises(ValueError, match="min_range"):
        KinectConfig(min_range=6.0)
    src = write_scene(office, tmp_path / "clean")
    with pytest.raises(CSAInputError, match="must differ"):
        degrade_scene_folder(src, src)
    (tmp_path / "taken").mkdir()
    with pytest.raises(CSAInputError, match="already exists"):
        degrade_scene_folder(src, tmp_path / "taken")


def test_degrade_command_writes_a_scene_folder(office: Scene, tmp_path, capsys) -> None:
    src = write_scene(office, tmp_path / "clean")
    dst = tmp_path / "hard"
    assert main(["data", "degrade", str(src), str(dst), "--seed", "2"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{dst}: 12 frames") and "label-noisy agrees with label-nyu40" in out
    back = read_scene(dst, labels="all")
    expected = degrade_scene(read_scene(src, labels="all"), seed=2)
    assert back.label_folders == sorted([NYU40_FOLDER, NOISY_FOLDER])
    for f, e in zip(back.frames, expected.frames, strict=True):
        np.testing.assert_array_equal(f.labels[NOISY_FOLDER], e.labels[NOISY_FOLDER])
        np.testing.assert_array_equal(f.color, e.color)
        np.testing.assert_allclose(f.depth, e.depth, atol=0.0006)  # stored in millimetres
    assert main(["data", "degrade", str(src), str(dst)]) == 2  # exists: refused, kept
    assert "already exists" in capsys.readouterr().err
    assert read_scene(dst).frames[0].depth is not None
