"""Checkpoints for the memory bank: one safetensors file, tensors + JSON metadata.

The file holds the field's parameters (float32 or float16), the occupancy grid (bit-packed),
the cells the training views' depth measured (bit-packed, ``visibility.py``), the training
poses, the per-frame colour corrections if the model has them (float32), and in the
safetensors header a JSON document with the config, the scene box, the camera, the class
list and the scene id, so loading needs nothing but the file.
Never pickle: a checkpoint is data, not code.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from csa_core.atomic_io import write_bytes_atomic
from csa_core.errors import CSAInputError
from csa_core.nerf.config import NerfConfig
from csa_core.nerf.model import SceneInfo, SemanticNerf
from csa_core.nerf.normalization import SceneBox

FORMAT = "csa-semantic-nerf"
VERSION = 1
_FIELD_PREFIX = "field."
_GRID_KEY = "occupancy_bits"
_POSES_KEY = "train_poses"
_APPEARANCE_KEY = "appearance"
_OBSERVED_KEY = "observed_bits"  # visibility.py; absent when no training view had depth


def checkpoint_bytes(nerf: SemanticNerf, dtype: str | None = None) -> bytes:
    """Serialise ``nerf``; ``dtype`` (``float32``/``float16``) defaults to the config's storage
    dtype."""
    dtype = dtype or nerf.config.storage_dtype
    if dtype not in ("float32", "float16"):
        raise ValueError(f"checkpoint dtype must be float32 or float16, got {dtype!r}")
    store = torch.float16 if dtype == "float16" else torch.float32
    tensors: dict[str, torch.Tensor] = {}
    for name, p in nerf.field.state_dict().items():
        tensors[_FIELD_PREFIX + name] = p.detach().to("cpu", store).contiguous()
        if not bool(torch.isfinite(tensors[_FIELD_PREFIX + name]).all()):
            # A diverged fit, or values beyond float16: never write a model that renders NaN.
            raise ValueError(
                f"checkpoint: parameter {name} is not finite as {dtype}; nothing written"
            )
    tensors[_GRID_KEY] = _pack_bits(nerf.grid.occupied)
    tensors[_POSES_KEY] = torch.as_tensor(np.asarray(nerf.info.train_poses, dtype=np.float64))
    if nerf.observed is not None and nerf.observed.marked:
        tensors[_OBSERVED_KEY] = _pack_bits(nerf.observed.cells)
    if nerf.appearance is not None:  # 6 numbers per training frame, kept in float32
        tensors[_APPEARANCE_KEY] = nerf.appearance.params.detach().to("cpu", torch.float32)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "dtype": dtype,
        "config": nerf.config.to_dict(),
        "box": nerf.box.to_dict(),
        "scene": nerf.info.to_dict(),
        "occupancy_resolution": nerf.grid.resolution,
    }
    return st_save(tensors, metadata={"csa": json.dumps(meta)})


def save_checkpoint(nerf: SemanticNerf, path: str | Path, dtype: str | None = None) -> int:
    """Write ``nerf`` to ``path`` atomically; returns the file size in bytes."""
    data = checkpoint_bytes(nerf, dtype)
    write_bytes_atomic(path, data)
    return len(data)


def load_checkpoint(path: str | Path, device: str | torch.device | None = "cpu") -> SemanticNerf:
    """Read a checkpoint written by :func:`save_checkpoint`; any damage raises
    :class:`CSAInputError` naming the file."""
    from csa_core.device import resolve_device

    path = Path(path)
    if not path.is_file():
        raise CSAInputError(path, "checkpoint not found")
    try:
        data = path.read_bytes()
        nerf = _from_bytes(data)
    except CSAInputError as e:
        raise CSAInputError(path, e.problem) from None
    except (
        SafetensorError,
        ValueError,
        KeyError,
        TypeError,
        RuntimeError,
        json.JSONDecodeError,
    ) as e:
        raise CSAInputError(
            path, f"not a readable CSA NeRF checkpoint ({type(e).__name__}: {e})"
        ) from None
    return nerf.to(resolve_device(device))


def _from_bytes(data: bytes) -> SemanticNerf:
    tensors = st_load(data)
    meta = _read_metadata(data)
    if meta.get("format") != FORMAT:
        raise CSAInputError("checkpoint", f"format is {meta.get('format')!r}, expected {FORMAT!r}")
    if int(meta.get("version", -1)) > VERSION:
        raise CSAInputError(
            "checkpoint",
            f"written by a newer version ({meta['version']}) than this reader ({VERSION})",
        )
    config = NerfConfig.from_dict(meta["config"])
    box = SceneBox.from_dict(meta["box"])
    info = SceneInfo.from_dict(meta["scene"], tensors[_POSES_KEY].numpy())
    nerf = SemanticNerf(config, box, info)
    state = {
        k[len(_FIELD_PREFIX) :]: v.float()
        for k, v in tensors.items()
        if k.startswith(_FIELD_PREFIX)
    }
    bad = [k for k, v in state.items() if not bool(torch.isfinite(v).all())]
    if bad:
        raise CSAInputError(
            "checkpoint", f"parameter {bad[0]} holds NaN or infinite values (a damaged file)"
        )
    nerf.field.load_state_dict(state, strict=True)
    if nerf.appearance is not None:
        if _APPEARANCE_KEY not in tensors:
            raise CSAInputError("checkpoint", "config has per-frame appearance but no tensor")
        nerf.appearance.params.data.copy_(tensors[_APPEARANCE_KEY].float())
    r = int(meta["occupancy_resolution"])
    _unpack_bits(tensors[_GRID_KEY], nerf.grid.occupied, r, "occupancy grid")
    if _OBSERVED_KEY in tensors:
        if nerf.observed is None:
            raise CSAInputError("checkpoint", "observed cells stored but observed_resolution is 0")
        _unpack_bits(
            tensors[_OBSERVED_KEY], nerf.observed.cells, nerf.observed.resolution, "observed cells"
        )
    nerf.eval()
    return nerf


def _pack_bits(grid: torch.Tensor) -> torch.Tensor:
    """A boolean grid as bytes, 8 cells each."""
    return torch.from_numpy(np.packbits(grid.detach().cpu().numpy().reshape(-1)))


def _unpack_bits(packed: torch.Tensor, grid: torch.Tensor, r: int, what: str) -> None:
    """Fill the boolean ``grid`` (r, r, r) from :func:`_pack_bits`' bytes."""
    bits = np.unpackbits(packed.numpy())[: r**3]
    if bits.size != r**3:
        raise CSAInputError("checkpoint", f"{what} is truncated")
    grid.copy_(torch.from_numpy(bits.astype(bool)).reshape(r, r, r))


def _read_metadata(data: bytes) -> dict:
    """The JSON document stored under ``csa`` in the safetensors header."""
    if len(data) < 8:
        raise CSAInputError("checkpoint", "file is too short to be a safetensors file")
    n = int.from_bytes(data[:8], "little")
    if n <= 0 or 8 + n > len(data):
        raise CSAInputError("checkpoint", "truncated safetensors header")
    header = json.loads(data[8 : 8 + n])
    meta = header.get("__metadata__", {}).get("csa")
    if meta is None:
        raise CSAInputError(
            "checkpoint", "no CSA metadata in the safetensors header (not a CSA NeRF checkpoint)"
        )
    return json.loads(meta)


def checkpoint_info(path: str | Path) -> dict:
    """The checkpoint's metadata (config, box, scene, dtype) plus its size, without building the
    model."""
    path = Path(path)
    try:
        data = path.read_bytes()
        meta = _read_metadata(data)
    except CSAInputError as e:
        raise CSAInputError(path, e.problem) from None
    except (OSError, ValueError, json.JSONDecodeError) as e:
        raise CSAInputError(path, f"not a readable CSA NeRF checkpoint ({e})") from None
    meta["bytes"] = len(data)
    return meta
