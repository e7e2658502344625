"""Importer for the Microsoft 7-Scenes layout into a scene folder.

7-Scenes: ``frame-XXXXXX.color.(jpg|png)``, ``frame-XXXXXX.depth.png`` (uint16 mm,
65535 = invalid), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world) and, where present,
``camera-intrinsics.txt`` (3x3). Without that file the data set's published intrinsics
(fx = fy = 585, principal point at the image centre) are used.

Those poses and intrinsics are the depth camera's; the colour images come from the Kinect's
colour camera, a few centimetres to the side with a wider view. By default (``camera="color"``)
the importer moves every frame to the colour camera (:mod:`csa_core.data.registration`):
colour-camera poses and intrinsics, depth splatted into the colour image at full resolution
before resizing. Then a pixel's colour, depth and pose agree, which the NeRF needs (held-out
PSNR 20.6 dB instead of 14.4 dB on the red kitchen, benchmarks/results/components.md
"7-Scenes red kitchen"). ``camera="depth"`` keeps the raw depth-camera frames, colour read as
if the depth camera had taken it.
"""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from csa_core.data import image_files as imf
from csa_core.data.camera import Intrinsics
from csa_core.data.registration import KINECT_V1_COLOR, ColorCamera, color_pose, register_depth
from csa_core.data.resample import resample_nearest, resize_color
from csa_core.data.scene import Frame, Scene, SkippedFrame
from csa_core.data.scene_io import write_scene
from csa_core.errors import CSAInputError

FRAME_RE = re.compile(r"^frame-(\d+)\.color\.(jpg|jpeg|png)$", re.IGNORECASE)
DEFAULT_FOCAL = 585.0  # 7-Scenes documentation: Kinect v1 colour and depth focal length
CAMERAS = ("color", "depth")


def load_7scenes(
    src: str | Path,
    every: int = 1,
    size: tuple[int, int] | None = None,
    camera: str = "color",
    color_camera: ColorCamera = KINECT_V1_COLOR,
) -> Scene:
    """Read a 7-Scenes sequence folder into a :class:`Scene` at working size ``size`` (W, H),
    seen from the colour camera ``color_camera`` (``camera="color"``) or from the depth camera
    whose poses the data set stores (``camera="depth"``)."""
    src = Path(src)
    if not src.is_dir():
        raise CSAInputError(src, "7-Scenes folder not found")
    if every < 1:
        raise CSAInputError("--every", f"must be >= 1, got {every}")
    if camera not in CAMERAS:
        raise CSAInputError("--camera", f"must be one of {', '.join(CAMERAS)}, got {camera!r}")
    found = sorted((int(m.group(1)), p) for p in src.iterdir() if (m := FRAME_RE.match(p.name)))
    if not found:
        raise CSAInputError(
            src, "no frame-XXXXXX.color.jpg files (is this a 7-Scenes sequence folder?)"
        )
    found = found[::every]
    first = imf.read_color(found[0][1])
    color_size = (first.shape[1], first.shape[0])
    k_path = src / "camera-intrinsics.txt"
    if k_path.is_file():
        cam = Intrinsics.from_matrix(imf.read_matrix(k_path, ((3, 3), (4, 4))), *color_size)
    else:
        cam = Intrinsics(
            DEFAULT_FOCAL, DEFAULT_FOCAL, color_size[0] / 2, color_size[1] / 2, *color_size
        )
    full = color_camera.at_size(*color_size) if camera == "color" else cam
    work = full.scaled(*size) if size is not None else full

    def load(item: tuple[int, Path]) -> Frame | SkippedFrame:
        idx, cpath = item
        stem = cpath.name.split(".color.")[0]
        pose_path = src / f"{stem}.pose.txt"
        if not pose_path.is_file():
            raise CSAInputError(pose_path, "pose file missing")
        pose = imf.read_matrix(pose_path, ((4, 4),))
        if not np.all(np.isfinite(pose)):
            return SkippedFrame(str(idx), f"{pose_path}: pose is not finite")
        if camera == "color":
            pose = color_pose(pose, color_camera)
        color = imf.read_color(cpath)
        if (color.shape[1], color.shape[0]) != color_size:
            raise CSAInputError(
                cpath,
                f"size mismatch: {color.shape[1]}x{color.shape[0]}, expected "
                f"{color_size[0]}x{color_size[1]}",
            )
        frame = Frame(name=str(idx), color=resize_color(color, work.width, work.height), pose=pose)
        dpath = src / f"{stem}.depth.png"
        if not dpath.is_file():
            raise CSAInputError(dpath, "depth file missing")
        mm = imf.read_depth_mm(dpath)
        depth = mm.astype(np.float32) / 1000.0  # 65535 (invalid) reads as 0
        depth_cam = cam.scaled(mm.shape[1], mm.shape[0])
        if camera == "color":
            depth = register_depth(depth, depth_cam, full, color_camera.offset)
            depth_cam = full
        frame.depth = resample_nearest(depth, depth_cam, work)
        return frame

    with ThreadPoolExecutor(max_workers=4) as pool:
        loaded = list(pool.map(load, found))
    frames = [f for f in loaded if isinstance(f, Frame)]
    skipped = [f for f in loaded if isinstance(f, SkippedFrame)]
    if not frames:
        raise CSAInputError(src, "no frame has a finite pose")
    return Scene(name=src.name, intrinsics=work, frames=frames, skipped=skipped, root=src)


def import_7scenes(
    src: str | Path,
    out: str | Path,
    every: int = 1,
    size: tuple[int, int] | None = None,
    overwrite: bool = False,
    camera: str = "color",
) -> Scene:
    """Convert a 7-Scenes sequence into a scene folder at ``out`` (colour stored as JPEG, like
    ScanNet), by default seen from the colour camera (see the module's docstring)."""
    scene = load_7scenes(src, every=every, size=size, camera=camera)
    write_scene(scene, out, overwrite=overwrite, color_ext=".jpg")
    return scene
