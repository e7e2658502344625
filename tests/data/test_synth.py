"""Procedural synthetic rooms: determinism, multi-view consistency, content, families, I/O."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from csa_core.data.camera import backproject, project
from csa_core.data.nyu40 import class_id
from csa_core.data.scene_io import read_scene
from csa_core.data.synth import (
    FAMILIES,
    family_names,
    generate_scene,
    parse_size,
    scene_seed,
    synthesize,
)
from csa_core.data.synth.boxes import BoxSet, any_hit, closest_hit, face_hit
from csa_core.data.synth.families import BASE_LOOKS
from csa_core.data.synth.floorplan import CELL_M, CLEARANCE_M
from csa_core.data.synth.generate import room_and_path
from csa_core.data.synth.render import room_solids
from csa_core.data.synth.textures import MaterialTable, albedo, has_look
from csa_core.errors import CSAInputError

NYU = "label-nyu40"
SHELL = {class_id("wall"), class_id("floor"), class_id("ceiling")}
# Seed of the steady rooms. (Seed 4's studio walk looks at a brick wall so closely and obliquely
# that 0.1 px of sampling offset crosses mortar lines on a fifth of the wall pixels.)
STEADY_SEED = 3


def _steady(name: str):
    """A family with fixed exposure and no sensor noise, so colours can be compared across views."""
    return dataclasses.replace(FAMILIES[name], exposure_jitter=0.0, sensor_noise=0.0)


@pytest.fixture(scope="module")
def steady_scenes():
    return {
        name: generate_scene(_steady(name), STEADY_SEED, 12, (128, 96)) for name in family_names()
    }


@pytest.fixture(scope="module")
def walk():
    return generate_scene("apartment", 7, 60, (48, 36))


# ---- determinism -------------------------------------------------------------------------


def test_same_seed_gives_bit_identical_scenes():
    a = generate_scene("studio", 11, 4, (64, 48))
    b = generate_scene("studio", 11, 4, (64, 48))
    assert a.intrinsics == b.intrinsics and a.name == b.name == "studio_11"
    for fa, fb in zip(a.frames, b.frames, strict=True):
        assert np.array_equal(fa.color, fb.color)
        assert np.array_equal(fa.depth, fb.depth)
        assert np.array_equal(fa.labels[NYU], fb.labels[NYU])
        assert np.array_equal(fa.pose, fb.pose)


def test_other_seeds_and_families_give_other_rooms():
    base = generate_scene("office", 1, 2, (48, 36))
    other_seed = generate_scene("office", 2, 2, (48, 36))
    other_family = generate_scene("apartment", 1, 2, (48, 36))
    for other in (other_seed, other_family):
        assert not np.allclose(base.frames[0].pose, other.frames[0].pose)
        assert np.mean(base.frames[0].depth != other.frames[0].depth) > 0.5
    assert len({scene_seed(3, k) for k in range(50)} | {scene_seed(4, k) for k in range(50)}) == 100


# ---- geometry and multi-view consistency -------------------------------------------------


def _correspondences(scene, i: int, j: int, tol_m: float = 0.015):
    """Pixels of view i whose back-projected point view j sees on the same surface: their
    flat indices in view i, the nearest pixel (u, v) in view j, and whether the point
    projects within 0.1 px of that pixel's centre (so both views sample nearly the same point)."""
    a, b, intr = scene.frames[i], scene.frames[j], scene.intrinsics
    pts = backproject(a.depth, intr, a.pose).reshape(-1, 3)
    uv, z = project(pts, intr, b.pose)
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = np.nonzero((z > 0) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height))[0]
    same = inside[np.abs(z[inside] - b.depth[v[inside], u[inside]]) < tol_m]
    centred = np.all(np.abs(uv[same] - np.round(uv[same])) < 0.1, axis=1)
    return same, u[same], v[same], centred


@pytest.mark.parametrize("family", family_names())
def test_reprojected_depth_sees_the_same_labels_and_colours(steady_scenes, family):
    scene = steady_scenes[family]
    n_px = scene.intrinsics.width * scene.intrinsics.height
    for i, j in ((0, 3), (0, 11)):
        idx, u, v, centred = _correspondences(scene, i, j)
        assert len(idx) > 0.3 * n_px, "views of one walk should share much of the scene"
        la = scene.frames[i].labels[NYU].reshape(-1)[idx]
        lab_b = scene.frames[j].labels[NYU]
        lb = lab_b[v, u]
        assert np.mean(la == lb) > 0.99
        # Away from label boundaries of view j (where rounding to a pixel can cross an edge),
        # the labels agree everywhere.
        pad = np.pad(lab_b, 1, mode="edge")
        interior = np.all([pad[v + dy, u + dx] == lb for dy in range(3) for dx in range(3)], axis=0)
        assert interior.sum() > 0.25 * n_px
        assert np.mean(la[interior] == lb[interior]) >= 0.999
        ca = scene.frames[i].color.reshape(-1, 3)[idx].astype(int)
        cb = scene.frames[j].color[v, u].astype(int)
        diff = np.abs(ca - cb).max(axis=1)
        # Nearest-pixel sampling differs on fine textures (wood grain, chair legs), so only
        # the median is tight here; the check below compares the same surface point.
        assert np.median(diff) <= 1 and diff.mean() < 5
        # Where both views sample (nearly) the same point, colour is the same up to rounding.
        assert centred.sum() > 150
        assert np.mean(diff[centred] <= 1) > 0.85


def test_depth_is_z_depth_of_points_inside_the_closed_room(steady_scenes):
    for family, scene in steady_scenes.items():
        room, _ = room_and_path(_steady(family), STEADY_SEED, 12)
        for f in scene.frames:
            assert (
                f.depth.dtype == np.float32
                and f.color.dtype == np.uint8
                and f.labels[NYU].dtype == np.uint8
            )
            assert np.all(np.isfinite(f.depth)) and f.depth.min() > 0.2
            assert f.depth.max() < math.hypot(room.width, room.depth, room.height)
            assert np.all(f.labels[NYU] > 0)
            pts = backproject(f.depth, scene.intrinsics, f.pose).reshape(-1, 3)
            assert np.all(pts >= -1e-3) and np.all(pts <= room.hi + 1e-3)
            on_floor = (f.labels[NYU] == class_id("floor")).reshape(-1)
            assert np.allclose(pts[on_floor, 2], 0.0, atol=1e-3)


def test_intrinsics_are_a_plausible_pinhole(steady_scenes):
    for scene in steady_scenes.values():
        k = scene.intrinsics
        hfov = math.degrees(2 * math.atan(k.width / 2 / k.fx))
        assert 60 <= hfov <= 70 and k.fx == k.fy
        assert k.cx == (k.width - 1) / 2 and k.cy == (k.height - 1) / 2


def test_camera_walks_smoothly_through_free_space_upright():
    for family in family_names():
        fam = FAMILIES[family]
        room, poses = room_and_path(fam, 2, 60)
        R = poses[:, :3, :3]
        assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
        assert np.allclose(np.linalg.det(R), 1.0)
        assert np.all(R[:, 2, 1] < 0), "image y (down) must point downwards in the z-up world"
        pos = poses[:, :3, 3]
        lo, hi = fam.camera_height_m
        assert np.all(pos[:, 2] > lo - 0.05) and np.all(pos[:, 2] < hi + 0.05)
        i, j = room.floor.cell_of(pos[:, :2])
        assert np.all(room.floor.clearance()[i, j] >= CLEARANCE_M - 2 * CELL_M)
        steps = np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1)
        assert steps.max() <= 1.05 * fam.step_m and steps.sum() > 0.5 * fam.step_m * 59
        cos_turn = (np.einsum("nij,nij->n", R[:-1], R[1:]) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos_turn, -1, 1))).max() < fam.max_turn_deg + 2.0


# ---- content ------------------------------------------------------------------------------


def test_a_walk_shows_walls_floor_and_at_least_eight_furniture_classes(walk):
    seen = set(np.unique(np.stack([f.labels[NYU] for f in walk.frames])).tolist())
    assert {class_id("wall"), class_id("floor")} <= seen
    assert len(seen - SHELL - {0}) >= 8


def _fill(solids, k: int) -> np.ndarray:
    """Points spread through solid ``k`` (its axis, inside and surface)."""
    nb = len(solids.boxes)
    if k < nb:
        g = np.linspace(-1.0, 1.0, 7)
        local = np.stack(np.meshgrid(g, g, g), axis=-1).reshape(-1, 3) * solids.boxes.half[k]
        return local @ solids.boxes.rot[k].T + solids.boxes.center[k]
    c = k - nb
    a, b, r = solids.caps.a[c], solids.caps.b[c], solids.caps.radius[c]
    ex, ey, _ = solids.caps.frame(np.array([c]))
    axis = a + np.linspace(0.0, 1.0, 15)[:, None] * (b - a)
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = 0.95 * r * (np.cos(ang)[:, None] * ex + np.sin(ang)[:, None] * ey)
    return np.concatenate([axis, (axis[:, None, :] + ring[None]).reshape(-1, 3)])


@pytest.mark.parametrize("family", family_names())
def test_layouts_hold_many_classes_and_nothing_interpenetrates(family):
    """Every solid lies inside the room, and solids of different objects (group, class,
    instance) never overlap by more than a millimetre, whatever their shape and tilt. Parts of
    one object may join (a spindle set into its seat, a tilted post meeting the seat)."""
    checked = 0
    for seed in range(3):
        room, _ = room_and_path(FAMILIES[family], seed, 2)
        solids, sources = room_solids(room)
        assert len({p.label for _, p in sources}) >= 8
        lo, hi = solids.aabb()
        assert np.all(lo >= -1e-6) and np.all(hi <= room.hi + 1e-6)
        obj = [(gi, p.label, p.instance) for gi, p in sources]
        # Pairs whose bounds come within 2 cm: touching objects (books on a board, a lamp on a
        # desk, chairs at a table) are checked too.
        near = np.all(lo[:, None, :] < hi[None, :, :] + 0.02, axis=-1) & np.all(
            lo[None, :, :] < hi[:, None, :] + 0.02, axis=-1
        )
        for i, j in zip(*np.nonzero(np.triu(near, 1)), strict=True):
            if obj[i] == obj[j]:
                continue
            for a, b in ((i, j), (j, i)):
                depth = solids.subset(np.array([b])).signed_distance(_fill(solids, a)).min()
                assert depth > -1e-3, (
                    f"{sources[a][1].label} and {sources[b][1].label} interpenetrate"
                )
            checked += 1
    assert checked > 50


@pytest.mark.parametrize("family", family_names())
def test_every_part_has_a_look_in_its_family(family):
    for seed in range(3):
        room, _ = room_and_path(FAMILIES[family], seed, 2)
        for g in room.groups:
            for p in g.group.parts:
                assert has_look(FAMILIES[family], p.label, p.role), (p.label, p.role)


def test_families_differ_in_appearance_of_the_same_classes():
    """Wall and floor colours, averaged over rooms, shift measurably between families."""
    means: dict[str, np.ndarray] = {}
    for family in family_names():
        pix: dict[int, list[np.ndarray]] = {}
        for seed in (0, 1, 2):
            for f in generate_scene(family, seed, 6, (64, 48)).frames:
                for c in (class_id("wall"), class_id("floor")):
                    pix.setdefault(c, []).append(f.color[f.labels[NYU] == c].astype(float))
        means[family] = np.concatenate([np.concatenate(pix[c]).mean(axis=0) for c in sorted(pix)])
    for a, b in itertools.combinations(family_names(), 2):
        assert np.linalg.norm(means[a] - means[b]) > 25, (a, b)


CORE = {"door", "window", "chair", "table", "sofa", "cabinet", "picture", "lamp", "box", "curtain"}


def test_families_share_a_core_of_classes_and_one_look_per_class():
    """Every family uses the same looks, and its rooms hold the same core classes (plus a few
    rarer family-specific ones), so a network trained on one family knows most classes of
    another."""
    seen: dict[str, set[str]] = {}
    for family in family_names():
        assert FAMILIES[family].looks == BASE_LOOKS
        labels: set[str] = set()
        for seed in range(6):
            room, _ = room_and_path(FAMILIES[family], seed, 2)
            labels |= {p.label for g in room.groups for p in g.group.parts}
        assert CORE <= labels, (family, CORE - labels)
        assert labels & {"bookshelf", "shelves"} and labels & {"bed", "desk"}
        seen[family] = labels
    for a, b in itertools.permutations(family_names(), 2):
        assert len(seen[a] & seen[b]) >= 0.75 * len(seen[a]), (a, b)


def test_each_room_draws_its_own_colours_around_the_family_shift():
    """Walls of different rooms of one family differ (no single colour per class), but the
    spread of one family overlaps the others: walls stay light and nearly neutral everywhere."""
    walls: dict[str, np.ndarray] = {}
    for family in family_names():
        fam = FAMILIES[family]
        cols = []
        for seed in range(40):
            rng = np.random.default_rng(seed)
            table = MaterialTable.for_room(fam.appearance, rng)
            table.add(fam.looks["wall"], rng, shell=True)
            cols.append(table.color1[0] ** (1 / 2.2) * 255)
        walls[family] = np.array(cols)
        assert walls[family].std(axis=0).mean() > 4
        assert walls[family].min() > 130
        sat = (walls[family].max(axis=1) - walls[family].min(axis=1)) / walls[family].max(axis=1)
        assert sat.mean() < 0.15
    for a, b in itertools.combinations(family_names(), 2):
        gap = np.linalg.norm(walls[a].mean(axis=0) - walls[b].mean(axis=0))
        assert gap < 3 * max(walls[a].std(axis=0).mean(), walls[b].std(axis=0).mean()), (a, b)


# ---- building blocks ----------------------------------------------------------------------


def test_slab_casting_matches_ray_marching():
    """Boxes turned about z and tilted about their own x axis."""
    rng = np.random.default_rng(0)
    boxes = BoxSet(
        rng.uniform(-2, 2, (6, 3)),
        rng.uniform(0.1, 0.6, (6, 3)),
        rng.uniform(0, 2 * np.pi, 6),
        rng.uniform(-0.6, 0.6, 6),
    )
    origin = np.array([0.1, -4.0, 0.2])
    dirs = rng.normal(0, 1, (300, 3)) * [0.5, 0.0, 0.5] + [0, 1, 0]
    t, idx = closest_hit(origin, dirs, boxes, np.full(len(dirs), np.inf))
    ts = np.linspace(0, 10, 4001)
    for k in range(len(dirs)):
        pts = origin + ts[:, None] * dirs[k]
        inside = np.zeros(len(ts), dtype=bool)
        for b in range(len(boxes)):
            local = boxes.to_local(pts, np.full(len(ts), b))
            inside |= np.all(np.abs(local) <= boxes.half[b], axis=1)
        if inside.any():
            assert idx[k] >= 0 and abs(t[k] - ts[np.argmax(inside)]) < 0.01
        else:
            assert idx[k] == -1
    hit = np.nonzero(idx >= 0)[0]
    t64, local, axis, normal = face_hit(origin, dirs[hit], boxes, idx[hit])
    assert np.allclose(t64, t[hit], atol=1e-4)
    assert np.allclose(np.abs(local[np.arange(len(hit)), axis]), boxes.half[idx[hit], axis])
    assert np.all(np.einsum("ij,ij->i", boxes.normal_to_world(normal, idx[hit]), dirs[hit]) < 0)
    assert np.array_equal(any_hit(origin, dirs, boxes, np.full(len(dirs), 10.0)), idx >= 0)


def test_textures_depend_only_on_the_surface_point():
    rng = np.random.default_rng(1)
    table = MaterialTable.empty()
    for fam in FAMILIES.values():
        for look in fam.looks.values():
            table.add(look, rng)
    mats = table.arrays()
    n = 2000
    mat = rng.integers(0, len(mats["pattern"]), n)
    pts = rng.uniform(-1, 1, (n, 3))
    axis = rng.integers(0, 3, n)
    whole = albedo(mats, mat, pts, axis)
    halves = np.concatenate(
        [
            albedo(mats, mat[:700], pts[:700], axis[:700]),
            albedo(mats, mat[700:], pts[700:], axis[700:]),
        ]
    )
    assert np.array_equal(whole, halves)
    assert whole.min() >= 0 and whole.max() <= 1 and whole.std() > 0.05


# ---- inputs and I/O -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "where"),
    [
        ({"family": "castle"}, "--family"),
        ({"size": (0, 48)}, "--size"),
        ({"size": (64,)}, "--size"),
        ({"size": "64x48"}, "--size"),
        ({"frames": 0}, "--frames"),
        ({"seed": -1}, "--seed"),
    ],
)
def test_bad_arguments_are_user_errors(kwargs, where):
    args = {"family": "office", "seed": 0, "frames": 2, "size": (64, 48)} | kwargs
    with pytest.raises(CSAInputError) as err:
        generate_scene(**args)
    assert err.value.where == where
    if where == "--family":
        assert "known: apartment, office, studio" in err.value.problem


def test_parse_size():
    assert parse_size("160x120") == (160, 120)
    for bad in ("160", "160*120", "x120", "0x10", "-5x10"):
        with pytest.raises(CSAInputError):
            parse_size(bad)


def test_synthesize_writes_scene_folders_that_read_back_exactly(tmp_path):
    with pytest.raises(CSAInputError):
        synthesize(tmp_path, scenes=0, frames=2, size=(64, 48), family="office", seed=5)
    paths = synthesize(tmp_path, scenes=2, frames=3, size=(64, 48), family="office", seed=5)
    assert [p.name for p in paths] == ["office_5_0", "office_5_1"]
    for k, path in enumerate(paths):
        ref = generate_scene("office", scene_seed(5, k), 3, (64, 48))
        back = read_scene(path)
        assert back.intrinsics.width == 64 and np.allclose(
            back.intrinsics.matrix(), ref.intrinsics.matrix()
        )
        for fr, fb in zip(ref.frames, back.frames, strict=True):
            assert np.array_equal(fr.labels[NYU], fb.labels[NYU])
            assert np.abs(fr.depth - fb.depth).max() <= 0.0005 + 1e-6
            assert np.array_equal(fr.color, fb.color)
            assert np.allclose(fr.pose, fb.pose, atol=1e-6)
    with pytest.raises(CSAInputError):
        synthesize(tmp_path, scenes=1, frames=2, size=(64, 48), family="office", seed=5)
    again = synthesize(
        tmp_path, scenes=1, frames=2, size=(64, 48), family="office", seed=5, overwrite=True
    )
    assert len(read_scene(again[0]).frames) == 2
