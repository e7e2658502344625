"""The voxel map's torch implementation against its numpy reference (``backend="numpy"``): the
same map, the same depth read-back, and the same ray casts (docs/method.md "Baselines"), but
for float rounding (float32 marches in torch, float64 in numpy) that could flip a crossing."""

from __future__ import annotations

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
    # Measured on CPU: every label and every hit equal, depths within 7 micrometres.
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


def test_torch_map_fuses_probabilities_like_the_reference(rooms) -> None:
    scene = rooms["office"]
    config = VoxelMapConfig(voxel_size=0.1, search_radius=2)
    reference, ported = fused_pair(scene, "cpu", config, probabilities=True)
    assert_same_map(reference, ported)
    labels, hits, depth_error = compare_reads(scene, reference, ported)
    assert labels >= 0.9995 and hits >= 0.9995 and depth_error < 1e-4  # measured 1, 1, 42 um


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
