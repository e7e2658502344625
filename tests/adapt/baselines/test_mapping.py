"""The Mapping baseline: voxel fusion of labels and pseudo-labels read back at training views."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.adapt.baselines import voxel_map as voxel_map_module
from csa_core.adapt.baselines.mapping import (
    build_voxel_map,
    mapping_adapt,
    mapping_memory,
    mapping_pseudo_labels,
    mapping_replay_buffer,
    render_map_labels,
)
from csa_core.adapt.baselines.voxel_map import (
    VoxelMapConfig,
    VoxelSemanticMap,
    pack_keys,
    unpack_keys,
    voxel_coords,
)
from csa_core.data.camera import Intrinsics, pixel_rays
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.data.synth import generate_scene
from csa_core.errors import CSAInputError
from csa_core.nerf.label_noise import corrupt_labels
from tests.tiny_scenes import look_at_pose


@pytest.fixture(scope="module")
def office() -> Scene:
    return generate_scene("office", 0, 16, (64, 48))


def agreement(labels: dict[str, np.ndarray], scene: Scene) -> float:
    """Fraction of pixels with depth whose label equals the ground truth."""
    hits = total = 0
    for frame in scene.frames:
        if frame.name not in labels:
            continue
        m = frame.depth > 0
        hits += int((labels[frame.name][m] == frame.labels[NYU40_FOLDER][m]).sum())
        total += int(m.sum())
    return hits / total


def test_ground_truth_fusion_reproduces_ground_truth(office: Scene) -> None:
    gt = {f.name: f.labels[NYU40_FOLDER] for f in office.frames}
    voxel_map = build_voxel_map(office, gt)
    # Read through each frame's own depth: measured 0.990 at 5 cm; the misses are pixels in
    # voxels shared by two surfaces.
    assert agreement(render_map_labels(voxel_map, office, list(gt), read="depth"), office) > 0.985
    # Ray casting stops at the first voxel a ray enters, so nearer objects grow by up to a
    # voxel (about a pixel here) over what lies behind them: measured 0.949.
    pseudo = mapping_pseudo_labels(office, gt)
    assert agreement(pseudo, office) > 0.94
    assert all((pseudo[f.name] > 0).all() for f in office.frames)  # every ray meets the room


def test_fusion_removes_view_inconsistent_noise(office: Scene) -> None:
    rng = np.random.default_rng(0)
    noisy = {f.name: corrupt_labels(f.labels[NYU40_FOLDER], rng) for f in office.frames}
    before = agreement(noisy, office)
    after = agreement(mapping_pseudo_labels(office, noisy), office)
    assert after > before + 0.1  # measured 0.67 -> 0.93


def test_points_in_one_cell_share_a_key() -> None:
    rng = np.random.default_rng(1)
    size = 0.05
    corner = np.array([3, -7, 12])
    inside = (corner + rng.uniform(0.001, 0.999, (200, 3))) * size
    keys = pack_keys(voxel_coords(inside, size))
    assert np.unique(keys).size == 1
    np.testing.assert_array_equal(unpack_keys(keys[:1])[0], corner)
    neighbours = (corner + np.eye(3) + 0.5) * size
    assert np.unique(pack_keys(voxel_coords(neighbours, size))).size == 3
    assert keys[0] not in pack_keys(voxel_coords(neighbours, size))


def flat_wall(depth_value: float, size=(80, 60)) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    w, h = size
    intr = Intrinsics(fx=60.0, fy=60.0, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)
    return np.full((h, w), depth_value, np.float32), np.eye(4), intr


def test_voxel_count_matches_surface_area() -> None:
    depth, pose, intr = flat_wall(2.025)  # in the middle of a 5 cm layer
    voxel_map = VoxelSemanticMap(VoxelMapConfig(voxel_size=0.05))
    voxel_map.integrate(np.ones(depth.shape, np.uint8), depth, pose, intr)
    area = (intr.width * 2.025 / intr.fx) * (intr.height * 2.025 / intr.fy)
    expected = area / 0.05**2
    assert 0.9 * expected <= voxel_map.num_voxels <= 1.3 * expected
    assert voxel_map.nbytes == voxel_map.num_voxels * (8 + 40 * 4)
    coarse = VoxelSemanticMap(VoxelMapConfig(voxel_size=0.1))
    coarse.integrate(np.ones(depth.shape, np.uint8), depth, pose, intr)
    assert coarse.num_voxels < voxel_map.num_voxels / 3


def box_in_front_of_a_wall(
    size=(80, 60),
) -> tuple[np.ndarray, np.ndarray, np.ndarray, Intrinsics]:
    """A wall 2.025 m away labelled 7 with a box face 1.525 m away labelled 5 in the middle."""
    depth, pose, intr = flat_wall(2.025, size)
    labels = np.full(depth.shape, 7, np.uint8)
    depth[20:40, 30:50] = 1.525
    labels[20:40, 30:50] = 5
    return depth, labels, pose, intr


def test_raycast_labels_a_depth_hole_over_an_object_the_map_knows() -> None:
    depth, labels, pose, intr = box_in_front_of_a_wall()
    scene = Scene(
        "box",
        intr,
        [
            Frame("0", np.zeros((*depth.shape, 3), np.uint8), pose, depth, {"p": labels}),
            Frame("1", np.zeros((*depth.shape, 3), np.uint8), pose, depth.copy(), {"p": labels}),
        ],
    )
    hole = np.zeros(depth.shape, bool)
    hole[22:38, 25:45] = True  # over the box and a strip of the wall
    scene.frames[1].depth[hole] = 0.0
    voxel_map = build_voxel_map(scene, {"0": labels})
    cast = render_map_labels(voxel_map, scene, ["1"])["1"]
    by_depth = render_map_labels(voxel_map, scene, ["1"], read="depth")["1"]
    assert (by_depth[hole] == 0).all()  # reading through the frame's depth misses the hole
    inner = np.zeros_like(hole)
    inner[23:37, 31:44] = True  # the hole over the box, one pixel from its outline
    assert (cast[inner] == 5).all()
    assert (cast[hole & (labels == 7)] == 7).mean() > 0.9  # the wall around it
    assert (cast > 0).all()
    # Away from the box's outline ray casting and the depth read-back agree.
    outline = np.zeros_like(hole)
    outline[18:42, 28:52] = True
    outline[22:38, 32:48] = False
    same = ~hole & ~outline
    np.testing.assert_array_equal(cast[same], by_depth[same])


def test_raycast_depth_first_surface_and_range() -> None:
    depth, labels, pose, intr = box_in_front_of_a_wall()
    voxel_map = VoxelSemanticMap()
    voxel_map.integrate(labels, depth, pose, intr)
    cast, z = voxel_map.raycast(pose, intr)
    # The box's face and the wall lie in the middle of a 5 cm voxel layer, so rays stop within
    # half a voxel (the middle of their stretch in the voxel) of the surface.
    assert np.abs(z - depth).max() <= 0.025 + 1e-6
    # A second wall behind the first, labelled 9, is hidden from the camera.
    behind = np.full_like(depth, 3.025)
    voxel_map.integrate(np.full(depth.shape, 9, np.uint8), behind, pose, intr)
    np.testing.assert_array_equal(voxel_map.raycast(pose, intr)[0], cast)
    # Turned round, the camera looks at nothing; with too short a range it reaches nothing.
    back = pose.copy()
    back[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    assert (voxel_map.labels_for_pose(back, intr) == 0).all()
    near = VoxelSemanticMap(VoxelMapConfig(max_range=1.4))
    near.integrate(labels, depth, pose, intr)
    assert (near.labels_for_pose(pose, intr) == 0).all()
    assert (VoxelSemanticMap().labels_for_pose(pose, intr) == 0).all()  # an empty map


def first_voxel_by_slabs(
    origin: np.ndarray, dirs: np.ndarray, cells: np.ndarray, size: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference: for each ray (unit ``dirs``), intersect every voxel box; the index of the box
    entered first, its entry and exit distances (-1 / inf where none)."""
    lo, hi = cells * size, (cells + 1) * size  # (V, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lo[None] - origin) / dirs[:, None, :]
        b = (hi[None] - origin) / dirs[:, None, :]
    t0 = np.nan_to_num(np.minimum(a, b), nan=-np.inf).max(axis=2)
    t1 = np.nan_to_num(np.maximum(a, b), nan=np.inf).min(axis=2)
    t0 = np.maximum(t0, 0.0)
    t0 = np.where(t0 < t1, t0, np.inf)
    first = t0.argmin(axis=1)
    rows = np.arange(dirs.shape[0])
    enter = t0[rows, first]
    return np.where(np.isfinite(enter), first, -1), enter, t1[rows, first]


@pytest.mark.parametrize("dense", [True, False])
def test_raycast_is_exact_voxel_traversal(dense: bool, monkeypatch) -> None:
    """Against intersecting each ray with every voxel box: the same first voxel for every ray
    (both the dense march grid and, for very large maps, the sorted keys)."""
    if not dense:
        monkeypatch.setattr(voxel_map_module, "MAX_DENSE_CELLS", 0)
    rng = np.random.default_rng(3)
    size = 0.1
    cells = np.unique(rng.integers(-6, 6, (40, 3)), axis=0)[:40]
    voxel_map = VoxelSemanticMap(VoxelMapConfig(voxel_size=size))
    scores = np.zeros((len(cells), 40), np.float32)
    scores[np.arange(len(cells)), np.arange(len(cells))] = 1.0  # voxel k has class k + 1
    voxel_map._add(pack_keys(cells), scores)
    intr = Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
    for eye in ([2.0, 1.3, 0.7], [0.05, -0.02, 0.11], [-1.7, 0.4, -2.2]):
        pose = look_at_pose(eye, rng.normal(0, 0.2, 3))
        labels, z = voxel_map.raycast(pose, intr)
        origins, dirs = pixel_rays(intr, pose)
        d = dirs.reshape(-1, 3)
        norm = np.linalg.norm(d, axis=1)
        first, enter, leave = first_voxel_by_slabs(origins[0, 0], d / norm[:, None], cells, size)
        # Rays that graze an edge or a corner can go either way: leave them out.
        clear = (first < 0) | (leave - enter > 1e-6)
        expected = np.where(first >= 0, first + 1, 0)
        np.testing.assert_array_equal(labels.ravel()[clear], expected[clear])
        hit = clear & (first >= 0)
        assert hit.sum() > 50 and (clear & (first < 0)).sum() > 50
        mid = 0.5 * (enter + leave) / norm
        np.testing.assert_allclose(z.ravel()[hit], mid[hit], atol=1e-5)


def test_search_radius_closes_gaps_rays_slip_through() -> None:
    depth, pose, intr = flat_wall(2.025, size=(40, 30))
    labels = np.full(depth.shape, 3, np.uint8)
    gap = np.zeros(depth.shape, bool)
    gap[:, 16:24] = True  # 8 pixels of the wall that no frame saw: 6 empty voxels (30 cm)
    seen = np.where(gap, 0.0, depth).astype(np.float32)
    plain = VoxelSemanticMap()
    plain.integrate(labels, seen, pose, intr)
    cast = plain.labels_for_pose(pose, intr)
    assert (cast[gap] == 0).all() and (cast[~gap] == 3).all()
    searching = VoxelSemanticMap(VoxelMapConfig(search_radius=3))
    searching.integrate(labels, seen, pose, intr)
    assert (searching.labels_for_pose(pose, intr) == 3).all()


def test_probabilities_and_votes_fuse_alike() -> None:
    depth, pose, intr = flat_wall(2.0, size=(40, 30))
    rng = np.random.default_rng(2)
    labels = rng.integers(1, 41, depth.shape).astype(np.uint8)
    one_hot = np.eye(40, dtype=np.float32)[labels - 1]
    votes, probs = VoxelSemanticMap(), VoxelSemanticMap()
    votes.integrate(labels, depth, pose, intr)
    probs.integrate(one_hot, depth, pose, intr)
    np.testing.assert_array_equal(votes.keys, probs.keys)
    np.testing.assert_allclose(votes.scores, probs.scores)
    unknown = VoxelSemanticMap()
    unknown.integrate(np.zeros(depth.shape, np.uint8), depth, pose, intr)
    assert unknown.num_voxels == 0


def test_bad_inputs_name_the_problem(office: Scene) -> None:
    with pytest.raises(CSAInputError, match="no frame"):
        mapping_pseudo_labels(office, {"nope": office.frames[0].labels[NYU40_FOLDER]})
    no_depth = Scene(
        "flat",
        office.intrinsics,
        [Frame(name="0", color=office.frames[0].color, pose=np.eye(4))],
    )
    with pytest.raises(CSAInputError, match="depth"):
        build_voxel_map(no_depth, {"0": office.frames[0].labels[NYU40_FOLDER]})


def test_memory_footprint_and_replay_split(office: Scene) -> None:
    gt = {f.name: f.labels[NYU40_FOLDER] for f in office.train_frames}
    voxel_map = build_voxel_map(office, gt)
    memory = mapping_memory(office, gt, voxel_map)
    fp = memory.footprint()
    w, h = office.size
    assert fp.image_bytes == len(gt) * w * h * 3
    assert fp.label_bytes == len(gt) * w * h
    assert fp.total_bytes == voxel_map.nbytes + fp.image_bytes + fp.label_bytes
    assert 0 < memory.footprint(".png").image_bytes < fp.image_bytes
    second = mapping_memory(office, gt, voxel_map)
    second.scene = "second"
    buffer = mapping_replay_buffer([memory, second], size=5)
    assert buffer.per_scene() == {office.name: 3, "second": 2}
    assert buffer.names[:3] == [f"{office.name}/{n}" for n in ("0", "6", "12")]


def test_mapping_step_end_to_end(office: Scene) -> None:
    import torch

    from csa_core.seg.config import TrainConfig
    from csa_core.seg.models import build_model

    torch.manual_seed(0)
    model = build_model("lraspp_mobilenet_v3_large")
    before = [p.detach().clone() for p in model.parameters()]
    gt = {f.name: f.labels[NYU40_FOLDER] for f in office.frames}
    earlier = mapping_memory(office, {n: gt[n] for n in ("0", "1", "2")})
    earlier.scene = "earlier"
    step = mapping_adapt(
        model,
        office,
        train=TrainConfig(epochs=1, batch_size=4, lr=1e-3, precise_bn_images=0, progress=False),
        replay=mapping_replay_buffer([earlier], size=4),
        predictions=gt,
    )
    assert set(step.pseudo_labels) == {f.name for f in office.train_frames}
    # Ray cast from the training views: nearer objects grow by up to a 5 cm voxel, about a
    # pixel at 64x48 (measured 0.951 on this room)
    assert agreement(step.pseudo_labels, office) > 0.94
    assert len(step.memory) == office.num_train and step.map_bytes > 0
    # 13 current + 4 replayed pairs in batches of 4, the incomplete last batch dropped.
    assert step.train_result is not None and step.train_result.images_seen == 16
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
