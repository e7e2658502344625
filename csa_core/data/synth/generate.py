"""Generate synthetic scenes in memory or write them as scene folders."""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np

from csa_core.data.camera import Intrinsics
from csa_core.data.camera import parse_size as camera_parse_size
from csa_core.data.scene import NYU40_FOLDER, Frame, Scene
from csa_core.data.scene_io import write_scene
from csa_core.data.synth.camera_path import CAPTURES, NoPathError, capture_poses
from csa_core.data.synth.families import RoomFamily, get_family
from csa_core.data.synth.layout import Room, build_room
from csa_core.data.synth.lighting import place_lights
from csa_core.data.synth.render import FrameRenderer, build_model
from csa_core.errors import CSAInputError, check_seed

MIN_SIDE_PX, MAX_SIDE_PX = 16, 4096
MAX_FRAMES = 100_000
LAYOUT_TRIES = 8


def _check(frames: int, size: tuple[int, int], seed: int) -> tuple[int, int]:
    if (
        isinstance(frames, bool)
        or not isinstance(frames, int | np.integer)
        or frames < 1
        or frames > MAX_FRAMES
    ):
        raise CSAInputError(
            "--frames", f"must be an integer between 1 and {MAX_FRAMES}, got {frames!r}"
        )
    check_seed(seed)
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise CSAInputError("--size", f"expected (width, height), got {size!r}") from None
    if not (MIN_SIDE_PX <= w <= MAX_SIDE_PX and MIN_SIDE_PX <= h <= MAX_SIDE_PX):
        raise CSAInputError(
            "--size",
            f"width and height must be between {MIN_SIDE_PX} and {MAX_SIDE_PX} pixels, got {w}x{h}",
        )
    return w, h


def parse_size(text: str) -> tuple[int, int]:
    """``"160x120"`` -> (160, 120) within the synthesiser's limits; a bad size is a user error
    naming ``--size``."""
    return _check(1, camera_parse_size(text), 0)


def intrinsics_for(width: int, height: int, hfov_deg: float) -> Intrinsics:
    """A centred pinhole camera with square pixels and the given horizontal field of view."""
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Intrinsics(
        fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height
    )


def _rng(family: RoomFamily, seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(family.name.encode()), stream])


def _exposures(family: RoomFamily, frames: int, rng: np.random.Generator) -> np.ndarray:
    """Per-frame exposure: the family's level times a slow random drift (auto-exposure)."""
    if family.exposure_jitter <= 0 or frames == 1:
        return np.full(frames, family.exposure)
    white = rng.normal(0.0, 1.0, frames + 24)
    k = np.exp(-0.5 * (np.arange(-12, 13) / 4.0) ** 2)
    drift = np.convolve(white, k / np.sqrt((k**2).sum()), mode="valid")[:frames]
    return family.exposure * np.exp(family.exposure_jitter * drift)


def check_capture(capture: str) -> str:
    """A capture mode name, or a user error naming ``--capture``."""
    if capture not in CAPTURES:
        raise CSAInputError(
            "--capture", f"unknown capture mode {capture!r} (known: {', '.join(CAPTURES)})"
        )
    return capture


def room_and_path(
    family: RoomFamily, seed: int, frames: int, capture: str = "walk"
) -> tuple[Room, np.ndarray]:
    """The room of (family, seed) and the camera poses of the capture mode in it: "walk" (a
    smooth walk through the room) or "random" (viewpoints spread at random through its free
    space, ``camera_path.random_views``). Both modes get the same room of (family, seed) unless
    its layout leaves one of them no room for the camera (then the next layout is drawn)."""
    rng = _rng(family, seed, 0)
    for attempt in range(LAYOUT_TRIES):
        room = build_room(family, rng, free_groups=attempt < LAYOUT_TRIES - 1)
        try:
            return room, capture_poses(room, family, frames, rng, check_capture(capture))
        except NoPathError:
            continue
    raise RuntimeError(f"synth: no walkable layout for family {family.name!r}, seed {seed}")


def generate_scene(
    family: str | RoomFamily,
    seed: int,
    frames: int,
    size: tuple[int, int],
    name: str | None = None,
    capture: str = "walk",
) -> Scene:
    """A synthetic scene in memory: ``frames`` posed RGB-D frames of one procedural room.

    ``family`` is a name from ``FAMILIES`` (or a :class:`RoomFamily`, e.g. a modified copy);
    ``size`` is (width, height); ``capture`` is "walk" or "random" (see :func:`room_and_path`).
    Labels are under ``label-nyu40``. The result depends only on the arguments: the same call
    gives bit-identical arrays.
    """
    fam = get_family(family)
    w, h = _check(frames, size, seed)
    check_capture(capture)
    room, poses = room_and_path(fam, seed, frames, capture)
    look_rng = _rng(fam, seed, 1)
    lights = place_lights(fam, room, look_rng)
    model = build_model(room, fam, lights, look_rng)
    intr = intrinsics_for(w, h, fam.hfov_deg)
    renderer = FrameRenderer(model, intr)
    exposures = _exposures(fam, frames, _rng(fam, seed, 2))
    out = []
    for i, pose in enumerate(poses):
        color, depth, labels = renderer.render(
            pose, float(exposures[i]), fam.sensor_noise, _rng(fam, seed, 1000 + i)
        )
        out.append(
            Frame(name=str(i), color=color, pose=pose, depth=depth, labels={NYU40_FOLDER: labels})
        )
    return Scene(name=name or f"{fam.name}_{seed}", intrinsics=intr, frames=out)


def scene_seed(seed: int, index: int) -> int:
    """Seed of the ``index``-th scene of a batch started with ``seed`` (stable, well mixed)."""
    return int(
        np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint32)[0]
    )


def synthesize(
    out_dir: str | Path,
    scenes: int,
    frames: int,
    size: tuple[int, int],
    family: str = "apartment",
    seed: int = 0,
    overwrite: bool = False,
    capture: str = "walk",
) -> list[Path]:
    """Write ``scenes`` scene folders ``out_dir/<family>_<seed>_<k>`` (k = 0..scenes-1).

    Scene k is ``generate_scene(family, scene_seed(seed, k), ..., capture=capture)``. Each
    folder is written atomically; an existing one is an error unless ``overwrite``.
    """
    fam = get_family(family)
    _check(frames, size, seed)
    check_capture(capture)
    if isinstance(scenes, bool) or not isinstance(scenes, int | np.integer) or scenes < 1:
        raise CSAInputError("--scenes", f"must be a positive integer, got {scenes!r}")
    out = Path(out_dir)
    names = [f"{fam.name}_{seed}_{k}" for k in range(scenes)]
    if not overwrite:
        for n in names:
            if (out / n).exists():
                raise CSAInputError(
                    out / n, "output already exists (pass --overwrite to replace it)"
                )
    written = []
    for k, n in enumerate(names):
        scene = generate_scene(fam, scene_seed(seed, k), frames, size, name=n, capture=capture)
        written.append(write_scene(scene, out / n, overwrite=overwrite))
    return written
