"""Space labels: ground truth defined in 3D for scenes without labels
(``csa_core.data.space_labels``)."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.data.camera import Intrinsics
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.data.space_labels import (
    CEILING,
    FLOOR,
    WALL,
    SpaceLabelConfig,
    add_space_labels,
    fit_space_labelling,
    label_frame,
    label_shares,
    space_labels,
)
from csa_core.data.synth import generate_scene
from csa_core.errors import CSAInputError
from tests.tiny_scenes import make_random_scene


@pytest.fixture(scope="module")
def room() -> Scene:
    """A synthetic office (z up, exact depth) with its true labels."""
    return generate_scene("office", 0, 30, (80, 60))


def _copy(scene: Scene, transform: np.ndarray | None = None) -> Scene:
    """The scene without labels; its world moved by the rigid ``transform`` when given."""
    t = np.eye(4) if transform is None else transform
    frames = [
        Frame(name=f.name, color=f.color, pose=t @ f.pose, depth=f.depth) for f in scene.frames
    ]
    return Scene(name=scene.name, intrinsics=scene.intrinsics, frames=frames)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def test_same_seed_same_labels_other_seed_other_labels(room):
    first = space_labels(_copy(room), seed=3)
    again = space_labels(_copy(room), seed=3)
    other = space_labels(_copy(room), seed=4)
    assert all(np.array_equal(first[n], again[n]) for n in first)
    assert all(v.dtype == np.uint8 and v.shape == (60, 80) for v in first.values())
    assert not all(np.array_equal(first[n], other[n]) for n in first)
    # The seed moves the furniture and objects, not the floor and walls.
    for n in first:
        for c in (FLOOR, WALL):
            assert np.array_equal(first[n] == c, other[n] == c)


def test_a_point_gets_the_same_label_from_every_camera_that_sees_it(room):
    scene = _copy(room)
    labelling = fit_space_labelling(scene, seed=0)
    a, b = scene.frames[3], scene.frames[20]
    labels_a = label_frame(labelling, a, scene.intrinsics)
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(a.depth > 0)
    pick = rng.choice(len(ys), size=300, replace=False)
    k = scene.intrinsics
    seen = 0
    for y, x in zip(ys[pick], xs[pick], strict=True):
        z = float(a.depth[y, x])
        world = a.pose[:3, :3] @ np.array([(x - k.cx) / k.fx * z, (y - k.cy) / k.fy * z, z])
        world += a.pose[:3, 3]
        # Another camera, b's pose, whose centre pixel of a 3x3 image sees exactly that point.
        cam = b.pose[:3, :3].T @ (world - b.pose[:3, 3])
        if cam[2] <= 0.1:
            continue
        f = 50.0
        intr = Intrinsics(f, f, 1 - f * cam[0] / cam[2], 1 - f * cam[1] / cam[2], 3, 3)
        depth = np.zeros((3, 3), np.float32)
        depth[1, 1] = cam[2]
        view = Frame(name="b", color=np.zeros((3, 3, 3), np.uint8), pose=b.pose, depth=depth)
        out = label_frame(labelling, view, intr)
        assert out[1, 1] == labels_a[y, x]
        assert (out == 0).sum() == 8  # no depth, unknown
        seen += 1
    assert seen > 100


def test_corresponding_pixels_of_two_views_agree(room):
    """Pixels of two views that see the same surface point (exact depth) nearly always get the
    same label; only region boundaries, half a pixel apart, can differ."""
    scene = _copy(room)
    labels = space_labels(scene, seed=0)
    k = scene.intrinsics
    agree, total = 0, 0
    for i, j in [(2, 6), (10, 14), (20, 25)]:
        a, b = scene.frames[i], scene.frames[j]
        ys, xs = np.nonzero(a.depth > 0)
        z = a.depth[ys, xs].astype(np.float64)
        cam = np.stack([(xs - k.cx) / k.fx * z, (ys - k.cy) / k.fy * z, z], axis=1)
        world = cam @ a.pose[:3, :3].T + a.pose[:3, 3]
        in_b = (world - b.pose[:3, 3]) @ b.pose[:3, :3]
        front = in_b[:, 2] > 0.1
        u = np.rint(in_b[:, 0] / np.where(front, in_b[:, 2], 1) * k.fx + k.cx).astype(int)
        v = np.rint(in_b[:, 1] / np.where(front, in_b[:, 2], 1) * k.fy + k.cy).astype(int)
        ok = front & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
        u, v = np.where(ok, u, 0), np.where(ok, v, 0)
        visible = ok & (np.abs(b.depth[v, u] - in_b[:, 2]) < 0.02)  # not occluded in b
        same = labels[a.name][ys, xs] == labels[b.name][v, u]
        agree += int((same & visible).sum())
        total += int(visible.sum())
    assert total > 1000
    assert agree / total > 0.95


def test_pixels_without_depth_are_unknown_and_all_others_labelled():
    scene = make_random_scene(n=4, size=(32, 24), seed=1, labels=())
    labels = space_labels(scene, seed=0)
    for f in scene.frames:
        assert np.array_equal(labels[f.name] == 0, f.depth == 0)
        assert labels[f.name].max() <= 40
    scene.frames[1].depth = None
    with pytest.raises(CSAInputError, match="need depth"):
        space_labels(scene)


def test_floor_walls_and_ceiling_of_a_synthetic_room(room):
    labelling = fit_space_labelling(_copy(room), seed=0)
    assert labelling.up @ np.array([0.0, 0.0, 1.0]) > np.cos(np.radians(1.0))
    assert labelling.floor is not None and abs(labelling.floor.offset) < 0.02
    assert labelling.ceiling is not None
    assert len(labelling.walls) >= 2
    truth = np.concatenate([f.labels[NYU40_FOLDER].ravel() for f in room.frames])
    ours = np.concatenate([label_frame(labelling, f, room.intrinsics).ravel() for f in room.frames])
    assert _iou(truth == FLOOR, ours == FLOOR) > 0.7
    assert _iou(truth == WALL, ours == WALL) > 0.75
    assert _iou(truth == CEILING, ours == CEILING) > 0.5


def test_floor_and_walls_are_found_in_any_world_orientation(room):
    """7-Scenes' world is about y-down: up comes from the geometry, not from the world axes."""
    # z up -> y down, then a tilt of 10 degrees about x and a shift.
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    move = np.eye(4)
    move[:3, :3] = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ np.array(
        [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    )
    move[:3, 3] = (0.3, -1.2, 2.0)
    plain = space_labels(_copy(room), seed=0)
    moved_scene = _copy(room, move)
    moved = space_labels(moved_scene, seed=0)
    labelling = fit_space_labelling(moved_scene, seed=0)
    assert labelling.up @ (move[:3, :3] @ [0.0, 0.0, 1.0]) > np.cos(np.radians(1.0))
    for c in (FLOOR, WALL):
        a = np.concatenate([plain[n].ravel() == c for n in plain])
        b = np.concatenate([moved[n].ravel() == c for n in moved])
        assert _iou(a, b) > 0.95


def test_label_shares_look_like_a_room(room):
    scene = _copy(room)
    add_space_labels(scene, seed=0)
    shares = label_shares(scene)
    assert sum(shares.values()) == pytest.approx(1.0)
    assert len(shares) >= 8
    assert max(shares, key=shares.get) == WALL
    small = [c for c, v in shares.items() if v < 0.01]
    assert len(small) >= 2  # small objects, as in real rooms
    assert max(shares.values()) < 0.7
    assert set(scene.label_folders) == {NYU40_FOLDER}


def test_config_is_checked():
    with pytest.raises(ValueError, match="object_radius"):
        SpaceLabelConfig(object_radius=(0.3, 0.1))
    with pytest.raises(ValueError, match="voxel"):
        SpaceLabelConfig(voxel=0.0)


def test_the_real_kitchen_gets_floor_walls_and_objects(seven_scenes_dir):
    from csa_core.data.sevenscenes import load_7scenes

    scene = load_7scenes(seven_scenes_dir, every=5, size=(80, 60))
    labelling = add_space_labels(scene, seed=0)
    # 7-Scenes' world is about y-down; the cameras look down at a table, so up is not their y.
    assert labelling.up @ np.array([0.0, -1.0, 0.0]) > np.cos(np.radians(40.0))
    assert labelling.floor is not None and labelling.walls
    shares = label_shares(scene)
    assert shares[FLOOR] > 0.02 and shares[WALL] > 0.05
    assert len(shares) >= 8 and max(shares.values()) < 0.6
