"""The Mapping baseline: voxel fusion of labels and pseudo-labels read back at training views."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.adapt.baselines import voxel_map as voxel_map_module
from csa_core.adapt.baselines.mapping import (
    build_voxel_map,
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
from csa_core.data.label_noise import corrupt_labels
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.data.synth import generate_scene
from csa_core.errors import CSAInputError
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
    # Ray casting to the TSDF's zero crossing: measured 0.984 on rooms of boxes, 0.963 since
    # the rooms have thin parts (stopping at the first voxel with scores instead grew nearer
    # objects by up to a voxel: 0.949). The rest are pixels next to silhouettes, which a 5 cm
    # TSDF places within about half a voxel, and parts thinner than a voxel (2 cm chair legs
    # and spindles: a fifth of the chair pixels are missed).
    pseudo = mapping_pseudo_labels(office, gt)
    assert agreement(pseudo, office) > 0.955
    # Nearly every ray meets the room (measured: all but 0.07% of the pixels, at silhouettes).
    assert np.mean([(pseudo[f.name] > 0).mean() for f in office.frames]) > 0.998


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
    # Keys and 40 float scores per labelled voxel; key, distance and weight per TSDF voxel.
    assert voxel_map.nbytes == voxel_map.num_voxels * (8 + 40 * 4) + voxel_map.num_tsdf_voxels * 16
    assert voxel_map.num_tsdf_voxels > 4 * voxel_map.num_voxels  # the band, +-3 voxels deep
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


def box_outline(shape: tuple[int, int], width: int = 1) -> np.ndarray:
    """Pixels within ``width`` of the outline of the box of :func:`box_in_front_of_a_wall`."""
    near = np.zeros(shape, bool)
    near[20 - width : 40 + width, 30 - width : 50 + width] = True
    near[20 + width : 40 - width, 30 + width : 50 - width] = False
    return near


def test_raycast_stops_at_the_first_surface() -> None:
    depth, labels, pose, intr = box_in_front_of_a_wall()
    voxel_map = VoxelSemanticMap()
    voxel_map.integrate(labels, depth, pose, intr)
    cast, z = voxel_map.raycast(pose, intr)
    # Rays stop where the TSDF crosses zero: on the box's face or on the wall, within a
    # millimetre; only next to the box's outline do they miss by up to half a voxel.
    rest = ~box_outline(depth.shape)
    assert np.abs(z - depth)[rest].max() < 1e-3
    np.testing.assert_array_equal(cast[rest], labels[rest])
    # A wall 3.025 m away labelled 9, seen from behind the first, is hidden from the camera.
    beyond = pose.copy()
    beyond[2, 3] = 2.5
    voxel_map.integrate(np.full(depth.shape, 9, np.uint8), np.full_like(depth, 0.525), beyond, intr)
    np.testing.assert_array_equal(voxel_map.raycast(pose, intr)[0], cast)
    assert (voxel_map.labels_for_pose(beyond, intr) == 9).all()
    # Turned round, the camera looks at nothing; with too short a range it reaches nothing.
    back = pose.copy()
    back[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    assert (voxel_map.labels_for_pose(back, intr) == 0).all()
    near = VoxelSemanticMap(VoxelMapConfig(max_range=1.4))
    near.integrate(labels, depth, pose, intr)
    assert (near.raycast(pose, intr)[1] == 0).all()
    empty_labels, empty_depth = VoxelSemanticMap().raycast(pose, intr)  # an empty map
    assert (empty_labels == 0).all() and (empty_depth == 0).all()


def plane_depth(intr: Intrinsics, pose: np.ndarray, point, normal) -> np.ndarray:
    """Exact z-depth (H, W) of the plane through ``point`` with ``normal`` (0 where a ray
    misses it)."""
    origins, dirs = pixel_rays(intr, pose)
    n = np.asarray(normal, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(point) - origins) @ n) / (dirs @ n)
    return np.where(np.isfinite(t) & (t > 0), t, 0.0).astype(np.float32)


def test_raycast_finds_a_tilted_plane_from_a_new_view() -> None:
    """A plane tilted against the voxel grid, fused from three views and cast from a fourth:
    the ray-cast depth is the plane's within two millimetres (a ray stopped at the first
    voxel it enters misses by up to a voxel, 5 cm)."""
    intr = Intrinsics(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)
    point, normal = np.array([0.013, 0.021, 0.0]), np.array([0.35, -0.2, 1.0])
    normal /= np.linalg.norm(normal)
    target = point
    voxel_map = VoxelSemanticMap()
    for eye in ([0.4, -1.5, 2.1], [-0.5, -1.2, 2.3], [0.1, -0.6, 2.4]):
        pose = look_at_pose(eye, target)
        voxel_map.integrate(
            np.full((48, 64), 4, np.uint8), plane_depth(intr, pose, point, normal), pose, intr
        )
    pose = look_at_pose([0.0, -1.1, 2.2], target + [0.05, 0.0, 0.0])  # not one of the three
    expected = plane_depth(intr, pose, point, normal)
    labels, z = voxel_map.raycast(pose, intr)
    inner = np.zeros_like(z, bool)
    inner[8:-8, 8:-8] = True  # seen by the fused views
    assert (labels[inner] == 4).all()
    err = np.abs(z - expected)[inner]
    assert err.max() < 0.002 and np.median(err) < 0.0005  # measured 1.1 mm and 0.1 mm


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
def test_ray_march_is_exact_voxel_traversal(dense: bool, monkeypatch) -> None:
    """The ray cast's empty-space skip, against intersecting each ray with every voxel box:
    the same first voxel and entry distance for every ray (both the dense march grid and, for
    very large maps, the sorted keys)."""
    if not dense:
        monkeypatch.setattr(voxel_map_module, "MAX_DENSE_CELLS", 0)
    rng = np.random.default_rng(3)
    size = 0.1
    cells = np.unique(rng.integers(-6, 6, (40, 3)), axis=0)[:40]
    index = voxel_map_module._RayIndex(cells, size, radius=0)
    intr = Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
    for eye in ([2.0, 1.3, 0.7], [0.05, -0.02, 0.11], [-1.7, 0.4, -2.2]):
        pose = look_at_pose(eye, rng.normal(0, 0.2, 3))
        origins, dirs = pixel_rays(intr, pose)
        d = dirs.reshape(-1, 3)
        unit = d / np.linalg.norm(d, axis=1)[:, None]
        rays, start, end = index.clip(origins[0, 0], unit, 10.0)
        hit, t_in, cell = index.march(origins[0, 0], unit[rays], start, end)
        got = np.full(unit.shape[0], -1)
        got[rays[hit]] = [np.flatnonzero((cells == c).all(axis=1))[0] for c in cell[hit]]
        t = np.full(unit.shape[0], np.inf)
        t[rays[hit]] = t_in[hit]
        first, enter, leave = first_voxel_by_slabs(origins[0, 0], unit, cells, size)
        # Rays that graze an edge or a corner can go either way: leave them out.
        clear = (first < 0) | (leave - enter > 1e-6)
        np.testing.assert_array_equal(got[clear], first[clear])
        found = clear & (first >= 0)
        assert found.sum() > 50 and (clear & (first < 0)).sum() > 50
        np.testing.assert_allclose(t[found], enter[found], atol=1e-6)


def test_search_radius_labels_surfaces_without_votes() -> None:
    """The TSDF holds every surface with depth, labelled or not; a ray that meets one with no
    votes nearby takes those within ``search_radius`` voxels, or stays unknown."""
    depth, pose, intr = flat_wall(2.025, size=(40, 30))
    labels = np.full(depth.shape, 3, np.uint8)
    labels[:, 16:] = 0  # no vote right of column 16: about 40 cm of wall
    plain = VoxelSemanticMap(VoxelMapConfig(search_radius=0))
    plain.integrate(labels, depth, pose, intr)
    cast, z = plain.raycast(pose, intr)
    assert (z > 0).all()  # every ray meets the wall
    assert (cast[:, :15] == 3).all() and (cast[:, 20:] == 0).all()
    searching = VoxelSemanticMap(VoxelMapConfig(search_radius=3))
    searching.integrate(labels, depth, pose, intr)
    cast = searching.labels_for_pose(pose, intr)
    # 3 voxels (15 cm) reach 4 to 5 pixels past the last labelled column.
    assert (cast[:, :20] == 3).all() and (cast[:, 23:] == 0).all()


def test_tsdf_is_the_signed_distance_to_a_wall() -> None:
    """Voxels within the truncation (3 voxels) of a wall seen head-on hold their distance to
    it, positive in front; those deeper behind it are left out; a second frame averages in."""
    depth, pose, intr = flat_wall(2.0, size=(40, 30))
    voxel_map = VoxelSemanticMap()
    voxel_map.integrate(np.ones(depth.shape, np.uint8), depth, pose, intr)
    centres = (unpack_keys(voxel_map.tsdf_keys) + 0.5) * 0.05
    axis = (np.abs(centres[:, 0]) < 0.05) & (np.abs(centres[:, 1]) < 0.05)
    expected = np.clip(2.0 - centres[axis, 2], None, 0.15)
    np.testing.assert_allclose(voxel_map.tsdf[axis], expected, atol=2e-3)
    assert centres[:, 2].max() < 2.15 and centres[axis, 2].min() < 1.86
    # Behind the wall observations weigh less the deeper they lie.
    behind = axis & (centres[:, 2] > 2.06)
    assert (voxel_map.weights[behind] < 1).all() and (voxel_map.weights[axis & ~behind] == 1).all()
    nearer = depth - 0.01  # a second view of the wall, 1 cm nearer
    voxel_map.integrate(np.ones(depth.shape, np.uint8), nearer, pose, intr)
    z = voxel_map.raycast(pose, intr)[1]
    np.testing.assert_allclose(z, 1.995, atol=1e-3)  # the weighted mean surface


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
    np.testing.assert_array_equal(votes.tsdf, probs.tsdf)
    unknown = VoxelSemanticMap()
    unknown.integrate(np.zeros(depth.shape, np.uint8), depth, pose, intr)
    assert unknown.num_voxels == 0 and unknown.num_tsdf_voxels == votes.num_tsdf_voxels
    cast, z = unknown.raycast(pose, intr)
    assert (cast == 0).all() and (z > 0).all()  # the geometry is there, with no votes


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


def test_continual_mapping_step_end_to_end(office: Scene, monkeypatch) -> None:
    """The continual step's Mapping method, here on ground-truth predictions: map labels read
    back at the training views, the scene's pairs stored, an earlier scene's pairs replayed,
    the network trained."""
    import torch

    from csa_core.adapt import methods
    from csa_core.adapt.config import preset
    from csa_core.adapt.methods import ContinualState
    from csa_core.adapt.step import continual_step
    from csa_core.seg.models import build_model

    gt = {f.name: f.labels[NYU40_FOLDER] for f in office.frames}
    monkeypatch.setattr(
        methods,
        "predict_frames",
        lambda model, frames, device=None: {f.name: gt[f.name] for f in frames},
    )
    torch.manual_seed(0)
    model = build_model("lraspp_mobilenet_v3_large")
    before = [p.detach().clone() for p in model.parameters()]
    config = preset("tiny")
    config.seg.device, config.seg.epochs, config.replay.buffer_size = "cpu", 1, 4
    state = ContinualState.start(config, "mapping")
    earlier = mapping_memory(office, {n: gt[n] for n in ("0", "1", "2")})
    earlier.scene = "earlier"
    state.method.memories = [earlier]
    record = continual_step(state, model, office)
    assert [m.scene for m in state.method.memories] == ["earlier", office.name]
    memory = state.method.memories[-1]
    labels = dict(zip(memory.names, memory.labels, strict=True))
    assert set(labels) == {f.name for f in office.train_frames}
    # Ray cast from the training views (measured 0.984 on this room of boxes, 0.965 since it
    # has thin parts that a 5 cm TSDF loses: see the test of ground-truth fusion above)
    assert agreement(labels, office) > 0.955
    assert len(memory) == office.num_train and memory.map_bytes > 0
    assert record["num_voxels"] > 0 and record["stored_bytes"] == memory.footprint().total_bytes
    assert record["replay"] == {"earlier": 4}
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
