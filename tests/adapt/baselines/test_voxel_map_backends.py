"""The voxel map's torch implementation against its numpy reference (``backend="numpy"``): the
same map, the same depth read-back, and the same ray casts (docs/method.md "Baselines"), but
for float rounding (float32 marches in torch, float64 in numpy) that could flip a crossing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from csa_core.adapt.baselines import voxel_map as voxel_map_module
from csa_core.adapt.baselines.voxel_map import VoxelMapConfig, VoxelSemanticMap
from csa_core.data.camera import Intrinsics
from csa_core.data.label_noise import corrupt_labels
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.data.synth import degrade_scene, generate_scene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(scope="module")
def rooms() -> dict[str, Scene]:
    """A clean office and a Kinect-like apartment (noisy depth with holes)."""
    return {
        "office": generate_scene("office", 0, 12, (64, 48)),
        "apartment": degrade_scene(generate_scene("apartment", 1, 12, (64, 48)), 1),
    }


def fused_pair(
    scene: Scene, device: str, config: VoxelMapConfig | None = None, probabilities: bool = False
) -> tuple[VoxelSemanticMap, VoxelSemanticMap]:
    """The training frames of ``scene``, with per-frame label noise, fused by both backends."""
    rng = np.random.default_rng(4)
    reference = VoxelSemanticMap(config, backend="numpy")
    ported = VoxelSemanticMap(config, device=device)
    for frame in scene.train_frames:
        labels = corrupt_labels(frame.labels[NYU40_FOLDER], rng)
        if probabilities:
            soft = rng.dirichlet(np.ones(40), size=labels.shape).astype(np.float32)
            prediction = 0.5 * soft + 0.5 * np.eye(40, dtype=np.float32)[labels - 1]
        else:
            prediction = labels
        for voxel_map in (reference, ported):
            voxel_map.integrate(prediction, frame.depth, frame.pose, scene.intrinsics)
    return reference, ported


def assert_same_map(reference: VoxelSemanticMap, ported: VoxelSemanticMap) -> None:
    # Same cells, and the same float32 arithmetic per voxel: measured bitwise equal.
    np.testing.assert_array_equal(ported.tsdf_keys, reference.tsdf_keys)
    np.testing.assert_allclose(ported.tsdf, reference.tsdf, atol=1e-6)
    np.testing.assert_allclose(ported.weights, reference.weights, atol=1e-6)
    np.testing.assert_array_equal(ported.keys, reference.keys)
    np.testing.assert_allclose(ported.scores, reference.scores, rtol=1e-5, atol=1e-5)
    assert ported.nbytes == reference.nbytes


def compare_reads(
    scene: Scene, reference: VoxelSemanticMap, ported: VoxelSemanticMap
) -> tuple[float, float, float]:
    """Over every view (the fused ones and the held-out ones): the share of pixels whose ray
    cast label is equal, the share whose rays agree on meeting a surface, and the largest
    difference of the depths where both do; the depth read-back must be identical."""
    same = hit_same = pixels = 0
    worst = 0.0
    for frame in scene.frames:
        labels, depth = reference.raycast(frame.pose, scene.intrinsics)
        port_labels, port_depth = ported.raycast(frame.pose, scene.intrinsics)
        assert port_labels.dtype == np.uint8 and port_depth.dtype == np.float32
        same += int((labels == port_labels).sum())
        hit_same += int(((depth > 0) == (port_depth > 0)).sum())
        stop = (depth > 0) & (port_depth > 0)
        worst = max(worst, float(np.abs(depth - port_depth)[stop].max(initial=0.0)))
        pixels += labels.size
        np.testing.assert_array_equal(
            ported.labels_at_depth(frame.depth, frame.pose, scene.intrinsics),
            reference.labels_at_depth(frame.depth, frame.pose, scene.intrinsics),
        )
    return same / pixels, hit_same / pixels, worst


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("room", ["office", "apartment"])
def test_torch_map_matches_the_numpy_reference(rooms, room: str, device: str) -> None:
    scene = rooms[room]
    reference, ported = fused_pair(scene, device)
    assert ported.num_tsdf_voxels > 1000
    assert_same_map(reference, ported)
    labels, hits, depth_error = compare_reads(scene, reference, ported)
    # The ray casts ran on the map's device, through its dense distance field.
    assert ported._surface.field is not None and ported._surface.field.device.type == device
    # Measured on CPU: every label and every hit equal, depths within 10 micrometres.
    # The bounds leave room for rounding: a ray that grazes a surface can flip either way.
    assert labels >= 0.9995
    assert hits >= 0.9995
    assert depth_error < 1e-4


def test_torch_map_without_dense_grids_matches_too(rooms, monkeypatch) -> None:
    """Maps too large for dense grids gather and look up cells by their sorted keys."""
    monkeypatch.setattr(voxel_map_module, "MAX_DENSE_CELLS", 0)
    scene = rooms["office"]
    reference, ported = fused_pair(scene, "cpu")
    assert_same_map(reference, ported)
    assert ported._surface is None
    labels, hits, depth_error = compare_reads(scene, reference, ported)
    assert ported._surface.field is None  # the march walked every cell near surfaces
    assert labels >= 0.9995 and hits >= 0.9995 and depth_error < 1e-4  # measured 1, 1, 9 um


def test_rays_along_the_grid_axes_match_too(rooms) -> None:
    """Cameras whose axes are the grid's, with a pixel column and row on the optical axis: rays
    with direction components of exactly zero (they cross no plane of that axis)."""
    scene = rooms["office"]
    reference, ported = fused_pair(scene, "cpu")
    intr = Intrinsics(fx=40.0, fy=40.0, cx=32.0, cy=24.0, width=64, height=48)
    row = column = 0
    for frame in scene.frames[:3]:
        for c, s in ((1.0, 0.0), (0.0, 1.0)):  # the frames look towards +x and +y
            # Looking level along a horizontal grid axis, image rows going down (z is up): the
            # middle row's rays are level, the middle column's run along the grid axis.
            pose = frame.pose.copy()
            pose[:3, :3] = np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])
            labels, depth = reference.raycast(pose, intr)
            port_labels, port_depth = ported.raycast(pose, intr)
            row, column = row + (depth[24] > 0).sum(), column + (depth[:, 32] > 0).sum()
            assert (labels == port_labels).mean() >= 0.9995
            assert ((depth > 0) == (port_depth > 0)).mean() >= 0.9995
            stop = (depth > 0) & (port_depth > 0)
            assert np.abs(depth - port_depth)[stop].max(initial=0.0) < 1e-4
    assert row > 0 and column > 0  # measured 146 and 13 rays that met a surface


def test_torch_map_fuses_probabilities_like_the_reference(rooms) -> None:
    scene = rooms["office"]
    config = VoxelMapConfig(voxel_size=0.1, search_radius=2)
    reference, ported = fused_pair(scene, "cpu", config, probabilities=True)
    assert_same_map(reference, ported)
    labels, hits, depth_error = compare_reads(scene, reference, ported)
    assert labels >= 0.9995 and hits >= 0.9995 and depth_error < 1e-4  # measured 1, 1, 28 um


def test_device_and_backend_options() -> None:
    voxel_map = VoxelSemanticMap(device=torch.device("cpu"))
    assert voxel_map.backend == "torch" and voxel_map.device == torch.device("cpu")
    assert VoxelSemanticMap().device == torch.device("cpu")  # CPU unless told otherwise
    assert isinstance(voxel_map.keys, np.ndarray) and voxel_map.nbytes == 0
    with pytest.raises(ValueError, match="backend must be one of"):
        VoxelSemanticMap(backend="jax")
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="numpy reference runs on the CPU"):
            VoxelSemanticMap(backend="numpy", device="cuda")


@pytest.mark.parametrize("backend", ["torch", "numpy"])
def test_points_beyond_the_packable_range_are_an_error(backend: str) -> None:
    intr = Intrinsics(fx=30.0, fy=30.0, cx=7.5, cy=5.5, width=16, height=12)
    far = np.full((12, 16), 6e4, np.float32)  # 60 km: beyond 2^20 voxels of 5 cm
    with pytest.raises(ValueError, match="farther than 2"):
        VoxelSemanticMap(backend=backend).integrate(
            np.ones((12, 16), np.uint8), far, np.eye(4), intr
        )


@pytest.mark.parametrize("shape", [(9, 40, 13), (3, 40, 5), (1, 6, 2)])
def test_grow_is_a_chebyshev_dilation(shape) -> None:
    """``_grow`` (shifted ORs, doubling the reach) against a cube-shaped max pool."""
    torch.manual_seed(0)
    mask = torch.rand(shape) > 0.97
    for r in (1, 2, 5, 16, 32):
        padded = torch.nn.functional.pad(mask.float()[None, None], (r,) * 6)
        brute = torch.nn.functional.max_pool3d(padded, 2 * r + 1, stride=1)[0, 0] > 0
        assert torch.equal(voxel_map_module._grow(mask, r), brute), r


def test_skip_field_is_one_less_than_the_distance_to_the_stopping_cells() -> None:
    """Every cell's skip is one less than its Chebyshev distance to the nearest stopping cell
    up to ``_T_EXACT``, beyond that the largest ``_T_EXACT`` times a power of two below the
    distance, at most ``_T_SKIP``: a ray never skips over a stopping cell. A bar of observed
    free space 150 voxels long with a surface at one end and a pillar beside it."""
    voxel_map = VoxelSemanticMap()
    axes = torch.arange(150), torch.arange(4), torch.arange(3)
    cells = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).view(-1, 3)
    tsdf = torch.full((cells.shape[0],), 0.1)
    tsdf[(cells[:, 0] == 0) | ((cells[:, 0] == 40) & (cells[:, 1] == 3))] = -0.05
    voxel_map._tsdf_keys = voxel_map_module._t_pack(cells)  # sorted: x, then y, then z
    voxel_map._tsdf, voxel_map._weights = tsdf, torch.ones_like(tsdf)
    surface = voxel_map_module._t_surface(voxel_map)
    field = surface.field.view([int(n) + 1 for n in surface.field_top])
    pad = voxel_map_module._T_PIECES + 1
    field = field[pad:-pad, pad:-pad, pad:-pad]  # the voxels' box, padded by one cell
    grid = torch.stack(torch.meshgrid(*(torch.arange(n) for n in field.shape), indexing="ij"))
    grid = grid.view(3, -1).T.float()
    # Stopping cells: those within one cell of a voxel with a non-positive distance.
    surfaces = (cells[tsdf <= 0] + 1).float()  # the box starts a cell below the voxels
    near_surface = torch.cdist(grid, surfaces, p=math.inf).amin(dim=1) <= 1
    assert torch.equal(field.reshape(-1) < 0, near_surface)
    stops = (field < 0).nonzero().float()
    distance = torch.cdist(grid, stops, p=math.inf).amin(dim=1).long()
    expected = distance - 1
    r = voxel_map_module._T_EXACT
    while r <= voxel_map_module._T_SKIP:  # distances beyond r skip (at least) r
        expected = torch.where(distance > r, r, expected)
        r *= 2
    assert distance.max() > voxel_map_module._T_SKIP
    assert torch.equal(field.reshape(-1).long(), expected)
