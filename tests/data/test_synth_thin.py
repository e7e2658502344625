"""Synthetic rooms: thin, tilted and curved parts, and the random-viewpoint capture mode."""

from __future__ import annotations

import math

import numpy as np
import pytest

from csa_core.cli.main import main
from csa_core.data.nyu40 import class_id
from csa_core.data.scene_io import read_scene
from csa_core.data.synth import FAMILIES, generate_scene
from csa_core.data.synth.camera_path import RANDOM_CLEARANCE_M, RANDOM_HEIGHT_M, look_at_pose
from csa_core.data.synth.furniture import chair_design, chair_parts, make_group, office_chair_parts
from csa_core.data.synth.generate import intrinsics_for, room_and_path
from csa_core.data.synth.layout import PlacedGroup, Room
from csa_core.data.synth.lighting import place_lights
from csa_core.data.synth.render import FrameRenderer, build_model, room_solids
from csa_core.data.synth.solids import CapsuleSet, capsule_entry, capsule_entry_paired
from csa_core.errors import CSAInputError

NYU = "label-nyu40"
CHAIR = class_id("chair")


# ---- the capsule primitive ------------------------------------------------------------------


def _inside_capsules(pts: np.ndarray, caps: CapsuleSet) -> np.ndarray:
    """Whether each point lies in some capsule, by the definition: within radius of the segment."""
    inside = np.zeros(len(pts), dtype=bool)
    for a, b, r in zip(caps.a, caps.b, caps.radius, strict=True):
        ba = b - a
        s = np.clip((pts - a) @ ba / max(ba @ ba, 1e-12), 0.0, 1.0)
        inside |= np.linalg.norm(pts - (a + s[:, None] * ba), axis=1) <= r
    return inside


def test_capsule_casting_matches_ray_marching():
    """Tilted rods, thin spindles (1 cm) and balls (no segment), against a brute-force march."""
    rng = np.random.default_rng(3)
    a = rng.uniform(-1.5, 1.5, (7, 3))
    b = a + rng.normal(0.0, 0.6, (7, 3))
    b[0] = a[0]  # a ball
    b[1] = a[1] + [0.0, 0.0, 1.0]  # a vertical rod, parallel to some rays below
    caps = CapsuleSet(a, b, np.array([0.2, 0.005, 0.1, 0.3, 0.01, 0.05, 0.15]))
    origin = np.array([0.2, -4.0, 0.1])
    dirs = rng.normal(0, 1, (400, 3)) * [0.45, 0.0, 0.45] + [0, 1, 0]
    dirs[:5] = caps.a[1] + [0.0, 0.0, 0.3] - origin + rng.normal(0, 0.002, (5, 3))  # at the spindle
    t = capsule_entry(origin, dirs, caps)
    first = t.min(axis=1)
    ts = np.linspace(0, 8, 16001)
    for k in range(len(dirs)):
        inside = _inside_capsules(origin + ts[:, None] * dirs[k], caps)
        if inside.any():
            assert np.isfinite(first[k]) and abs(first[k] - ts[np.argmax(inside)]) < 2e-3
        else:
            assert not np.isfinite(first[k])
    hit = np.nonzero(np.isfinite(first))[0]
    assert len(hit) > 25 and np.isfinite(first[:5]).all()  # the 1 cm spindle is hit
    idx = np.argmin(t[hit], axis=1)
    exact = capsule_entry_paired(origin, dirs[hit], caps.subset(idx))
    assert np.allclose(exact, first[hit], atol=1e-4)
    surface = origin + exact[:, None] * dirs[hit]
    ba = caps.b[idx] - caps.a[idx]
    s = np.clip(
        np.einsum("ij,ij->i", surface - caps.a[idx], ba)
        / np.maximum(np.einsum("ij,ij->i", ba, ba), 1e-12),
        0,
        1,
    )
    dist = np.linalg.norm(surface - (caps.a[idx] + s[:, None] * ba), axis=1)
    assert np.allclose(dist, caps.radius[idx], atol=1e-9)


# ---- thin parts in rendered frames ------------------------------------------------------------


def _render_alone(parts, pose, size=(161, 121)):
    """Render ``parts`` (one group, in the middle of an empty 5 x 5 x 2.6 m room) from ``pose``."""
    room = Room(5.0, 5.0, 2.6)
    room.groups.append(PlacedGroup(make_group("test", parts, "free"), 2.5, 2.5, 0.0, None))
    fam = FAMILIES["office"]
    rng = np.random.default_rng(0)
    model = build_model(room, fam, place_lights(fam, room, rng), rng)
    intr = intrinsics_for(*size, 60.0)
    color, depth, labels = FrameRenderer(model, intr).render(pose, 1.0, 0.0, rng)
    return room, depth, labels, intr


def test_a_two_centimetre_leg_is_chair_at_its_depth_in_a_close_view():
    parts = chair_parts(
        np.random.default_rng(1), design=chair_design(np.random.default_rng(1), "tube")
    )
    room = Room(5.0, 5.0, 2.6)
    room.groups.append(PlacedGroup(make_group("test", parts, "free"), 2.5, 2.5, 0.0, None))
    solids, sources = room_solids(room)
    legs = [
        k
        for k, (_, p) in enumerate(sources)
        if p.shape == "rod" and abs(p.tilt) < 1e-9 and p.center[2] < 0.3
    ]
    k = legs[0] - len(solids.boxes)
    a, b, r = solids.caps.a[k], solids.caps.b[k], solids.caps.radius[k]
    assert 0.009 <= r <= 0.012 and a[2] < 0.02 and b[2] > 0.35  # 1.8-2.4 cm across, floor to seat
    target = np.array([a[0], a[1], 0.2])
    eye = target + [0.0, -0.8, 0.0]  # 80 cm in front of the leg, looking straight at it
    _, depth, labels, intr = _render_alone(parts, look_at_pose(eye, math.pi / 2, 0.0))
    cy, cx = intr.height // 2, intr.width // 2
    assert labels[cy, cx] == CHAIR
    assert depth[cy, cx] == pytest.approx(0.8 - r, abs=1e-4)
    leg_px = (labels[cy] == CHAIR) & (np.abs(depth[cy] - 0.8) < 0.02)
    left, right = cx, cx
    while leg_px[left - 1]:
        left -= 1
    while leg_px[right + 1]:
        right += 1
    width_px = 2 * r * intr.fx / 0.8
    assert abs((right - left + 1) - width_px) <= 1.5  # the leg is as wide in the image as it is
    # Beside the leg: what stands behind it (the chair's other leg or the room), farther away.
    beside = depth[cy, right + 1 : right + 8]
    assert np.all(beside > 0.8 + 0.2)


def test_slat_gaps_show_what_is_behind_the_back():
    design = chair_design(np.random.default_rng(2), "slat")
    parts = chair_parts(np.random.default_rng(2), design=design)
    slats = [
        p
        for p in parts
        if p.label == "chair" and p.role == "body" and p.half[2] > 0.05 and p.half[0] < 0.03
    ]
    assert len(slats) == design["slats"] >= 3
    z = slats[0].center[2]
    # From behind the chair (its back is at +y), 90 cm away, at the height of the slats' middle.
    group = make_group("test", parts, "free")
    y_back = max(p.center[1] for p in group.parts) + 2.5
    eye = np.array([2.5, y_back + 0.9, z])
    _, depth, labels, intr = _render_alone(parts, look_at_pose(eye, -math.pi / 2, 0.0))
    row_l, row_d = labels[intr.height // 2], depth[intr.height // 2]
    chair = row_l == CHAIR
    runs = np.flatnonzero(np.diff(chair.astype(int)) == 1)
    assert len(runs) >= design["slats"] + 1  # two posts and the slats between them, apart
    first, last = np.flatnonzero(chair)[[0, -1]]
    gaps = ~chair[first : last + 1]
    assert gaps.sum() >= 3
    near = row_d[first : last + 1][~gaps].max()
    assert np.all(row_d[first : last + 1][gaps] > near + 0.3)  # through a gap: the room beyond
    assert np.all(row_d[first : last + 1][~gaps] < 1.0)


def test_a_swivel_chair_base_has_five_spokes_and_castors_on_the_floor():
    parts = office_chair_parts(np.random.default_rng(4))
    rods = [p for p in parts if p.shape == "rod"]
    castors = [p for p in rods if p.half[2] == 0.0]
    assert len(castors) == 5
    assert all(abs(p.center[2] - p.half[0]) < 1e-9 for p in castors)  # resting on the floor
    spokes = [p for p in rods if p.half[2] > 0.1 and p.tilt > 1.0]
    assert len(spokes) == 5 and all(0.016 <= 2 * p.half[0] <= 0.022 for p in spokes)


def test_every_family_has_thin_tilted_and_curved_parts_and_many_chairs_in_offices():
    for name in FAMILIES:
        rooms = [room_and_path(FAMILIES[name], seed, 2)[0] for seed in range(3)]
        parts = [p for room in rooms for g in room.groups for p in g.group.parts]
        thin = [
            p
            for p in parts
            if min(p.half) * 2 <= 0.03 and p.label in ("chair", "table", "desk", "shelves", "lamp")
        ]
        assert len(thin) > 30, name
        assert any(p.shape == "box" and abs(p.tilt) > 0.05 for p in parts), name
        assert sum(p.shape == "rod" for p in parts) > 20, name
        chairs = [
            len(
                {
                    (gi, p.instance)
                    for gi, g in enumerate(r.groups)
                    for p in g.group.parts
                    if p.label == "chair"
                }
            )
            for r in rooms
        ]
        assert min(chairs) >= (4 if name == "office" else 1), (name, chairs)


# ---- the random capture --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def random_office():
    return generate_scene("office", 5, 24, (64, 48), capture="random")


def test_random_views_stand_in_free_space_and_look_at_something(random_office):
    room, poses = room_and_path(FAMILIES["office"], 5, 24, "random")
    assert np.array_equal(poses, np.stack([f.pose for f in random_office.frames]))
    pos = poses[:, :3, 3]
    assert np.all(pos[:, 2] >= RANDOM_HEIGHT_M[0]) and np.all(pos[:, 2] <= RANDOM_HEIGHT_M[1])
    assert np.all(pos[:, :2] >= RANDOM_CLEARANCE_M - 0.03) and np.all(
        pos[:, :2] <= room.hi[:2] - RANDOM_CLEARANCE_M + 0.03
    )
    solids, _ = room_solids(room)
    assert solids.signed_distance(pos).min() > 0.1  # inside no piece of furniture
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9) and np.allclose(
        np.linalg.det(R), 1.0
    )
    assert np.all(R[:, 2, 1] < 0)  # upright: image y points down
    # Spread through the room, not a walk: consecutive views are far apart.
    assert np.ptp(pos[:, 0]) > 0.4 * room.width and np.ptp(pos[:, 1]) > 0.4 * room.depth
    assert np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1)) > 0.8
    shell = {class_id("wall"), class_id("floor"), class_id("ceiling")}
    for f in random_office.frames:
        assert np.mean(f.depth < 0.3) <= 0.3
        assert set(np.unique(f.labels[NYU]).tolist()) - {class_id("wall")}
    seen = set(np.unique(np.stack([f.labels[NYU] for f in random_office.frames])).tolist())
    assert CHAIR in seen and len(seen - shell) >= 6


def test_random_capture_is_deterministic_per_seed_and_keeps_the_room():
    a = room_and_path(FAMILIES["studio"], 2, 6, "random")
    b = room_and_path(FAMILIES["studio"], 2, 6, "random")
    c = room_and_path(FAMILIES["studio"], 3, 6, "random")
    walk_room, walk = room_and_path(FAMILIES["studio"], 2, 6, "walk")
    assert np.array_equal(a[1], b[1]) and not np.allclose(a[1], c[1])
    assert [(g.x, g.y, g.yaw) for g in a[0].groups] == [(g.x, g.y, g.yaw) for g in walk_room.groups]
    assert not np.allclose(a[1], walk)


def test_capture_is_chosen_by_name_on_the_command_line(tmp_path, capsys):
    with pytest.raises(CSAInputError) as err:
        generate_scene("office", 0, 2, (32, 24), capture="orbit")
    assert err.value.where == "--capture" and "walk, random" in err.value.problem
    assert (
        main(
            [
                "data",
                "synth",
                str(tmp_path / "bad"),
                "--frames",
                "2",
                "--size",
                "32x24",
                "--capture",
                "orbit",
            ]
        )
        == 2
    )
    assert "--capture" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    argv = [
        "data",
        "synth",
        str(tmp_path),
        "--family",
        "studio",
        "--frames",
        "3",
        "--size",
        "32x24",
        "--capture",
        "random",
    ]
    assert main(argv) == 0
    back = read_scene(tmp_path / "studio_0_0")
    from csa_core.data.synth import scene_seed

    ref = generate_scene("studio", scene_seed(0, 0), 3, (32, 24), capture="random")
    for fr, fb in zip(ref.frames, back.frames, strict=True):
        assert np.allclose(fr.pose, fb.pose, atol=1e-6) and np.array_equal(
            fr.labels[NYU], fb.labels[NYU]
        )
