"""Checkpoints: bit-exact round trip, fp16 storage, and damaged files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from csa_core.errors import CSAInputError
from csa_core.nerf.checkpoint import checkpoint_info, load_checkpoint, save_checkpoint
from csa_core.nerf.render import render_image


def _render(nerf, pose):
    return render_image(nerf, pose, semantics=True)


def test_float32_round_trip_renders_bit_exact(tiny_nerf, tiny_scene, tmp_path):
    path = tmp_path / "scene.safetensors"
    size = save_checkpoint(tiny_nerf, path, dtype="float32")
    assert path.stat().st_size == size
    loaded = load_checkpoint(path)
    for name, p in tiny_nerf.field.state_dict().items():
        assert torch.equal(p, loaded.field.state_dict()[name]), name
    assert torch.equal(tiny_nerf.grid.occupied, loaded.grid.occupied)
    assert tiny_nerf.observed is None and loaded.observed is None  # none by default
    pose = tiny_scene.frames[-1].pose
    for sampler in ("occupancy", "reference"):
        a = render_image(tiny_nerf, pose, sampler=sampler)
        b = render_image(loaded, pose, sampler=sampler)
        assert (
            np.array_equal(a.color, b.color)
            and np.array_equal(a.depth, b.depth)
            and np.array_equal(a.labels, b.labels)
        )
    assert loaded.box == tiny_nerf.box
    assert loaded.info.intrinsics == tiny_nerf.info.intrinsics
    assert np.array_equal(loaded.info.train_poses, tiny_nerf.info.train_poses)
    assert loaded.config == tiny_nerf.config


def test_float16_is_half_the_size_and_reloads_stably(tiny_nerf, tiny_scene, tmp_path):
    s32 = save_checkpoint(tiny_nerf, tmp_path / "a.safetensors", dtype="float32")
    s16 = save_checkpoint(tiny_nerf, tmp_path / "b.safetensors", dtype="float16")
    # The bit-packed grids weigh the same in both: the field's tensors take half the bytes.
    field32 = sum(4 * p.numel() for p in tiny_nerf.field.state_dict().values())
    assert s32 - s16 > 0.45 * field32
    once = load_checkpoint(tmp_path / "b.safetensors")
    save_checkpoint(once, tmp_path / "c.safetensors", dtype="float16")
    twice = load_checkpoint(tmp_path / "c.safetensors")
    pose = tiny_scene.frames[0].pose
    a, b = render_image(once, pose), render_image(twice, pose)
    assert np.array_equal(a.color, b.color) and np.array_equal(a.labels, b.labels)
    info = checkpoint_info(tmp_path / "b.safetensors")
    assert info["dtype"] == "float16" and info["scene"]["name"] == tiny_scene.name
    assert info["scene"]["classes"][0] == "wall" and len(info["scene"]["classes"]) == 40


def test_observed_cells_round_trip(tiny_nerf, tiny_scene, tmp_path):
    import copy

    from csa_core.nerf.rays import RayBank
    from csa_core.nerf.visibility import ObservedCells

    nerf = copy.deepcopy(tiny_nerf)
    nerf.config.observed_resolution = 48
    nerf.observed = ObservedCells(48)
    nerf.observed.mark(
        nerf.box, RayBank(tiny_scene.train_frames, tiny_scene.intrinsics).surface_points()
    )
    path = tmp_path / "cells.safetensors"
    size = save_checkpoint(nerf, path)
    assert size > save_checkpoint(tiny_nerf, tmp_path / "plain.safetensors") + 48**3 // 8 - 64
    loaded = load_checkpoint(path)
    assert loaded.observed.marked and torch.equal(loaded.observed.cells, nerf.observed.cells)


def test_a_checkpoint_without_observed_cells_loads_and_uses_the_frusta(tiny_nerf, tmp_path):
    """Checkpoints written before the cells of measured surfaces (no ``observed_bits``, no
    ``observed_resolution`` in the config) load without them."""
    import copy

    nerf = copy.deepcopy(tiny_nerf)
    nerf.config.observed_resolution = 0
    nerf.observed = None
    path = tmp_path / "old.safetensors"
    save_checkpoint(nerf, path)
    data = path.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    meta = json.loads(header["__metadata__"]["csa"])
    assert "observed_bits" not in header
    del meta["config"]["observed_resolution"]
    header["__metadata__"]["csa"] = json.dumps(meta)
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(len(raw).to_bytes(8, "little") + raw + data[8 + n :])
    loaded = load_checkpoint(path)
    assert loaded.observed is None and loaded.config.observed_resolution == 0
    pts = torch.as_tensor(np.asarray(tiny_nerf.info.train_poses)[:, :3, 3], dtype=torch.float32)
    assert torch.equal(loaded.seen_surface_points(pts), loaded.seen_by_training_cameras(pts))


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "foreign", "header", "nan"])
def test_damaged_checkpoints_raise_input_errors_naming_the_file(tiny_nerf, tmp_path, damage):
    path = tmp_path / f"{damage}.safetensors"
    save_checkpoint(tiny_nerf, path)
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00" * 8 + bytes(range(256)) * 10)
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "foreign":
        from safetensors.torch import save_file

        save_file({"w": torch.zeros(3)}, str(path))
    elif damage == "header":
        n = int.from_bytes(data[:8], "little")
        header = json.loads(data[8 : 8 + n])
        meta = json.loads(header["__metadata__"]["csa"])
        del meta["config"]["field"]
        header["__metadata__"]["csa"] = json.dumps(meta)
        blob = json.dumps(header).encode()
        blob += b" " * (-len(blob) % 8)
        path.write_bytes(len(blob).to_bytes(8, "little") + blob + data[8 + n :])
    elif damage == "nan":  # flipped bits inside a tensor: the file still parses
        n = int.from_bytes(data[:8], "little")
        header = json.loads(data[8 : 8 + n])
        start, end = header["field.encoding.table"]["data_offsets"]
        body = bytearray(data)
        body[8 + n + start : 8 + n + end] = b"\xff" * (end - start)
        path.write_bytes(bytes(body))
    with pytest.raises(CSAInputError) as e:
        load_checkpoint(path)
    assert str(path) in str(e.value)
    if damage == "nan":
        assert "encoding.table holds NaN or infinite values" in str(e.value)


def test_a_model_with_parameters_that_are_not_finite_is_not_written(tiny_nerf, tmp_path):
    import copy

    broken = copy.deepcopy(tiny_nerf)
    with torch.no_grad():
        next(broken.field.parameters()).view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match="not finite"):
        save_checkpoint(broken, tmp_path / "nan.safetensors")
    assert list(tmp_path.iterdir()) == []


def test_missing_checkpoint_is_an_input_error(tmp_path):
    with pytest.raises(CSAInputError, match="not found"):
        load_checkpoint(tmp_path / "nope.safetensors")
