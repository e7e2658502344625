"""Reader and writer of the scene folder (ScanNet export layout, see
docs/data-contract.md "The scene folder")."""

from __future__ import annotations

import glob
import logging
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from csa_core.atomic_io import atomic_dir
from csa_core.data import image_files as imf
from csa_core.data.camera import Intrinsics, check_pose, intrinsics_from_matrix
from csa_core.data.resample import resample_nearest, resize_color
from csa_core.data.scannet_labels import load_raw_to_nyu40
from csa_core.data.scene import (
    NYU40_FOLDER,
    RAW_SCANNET_FOLDER,
    Frame,
    Scene,
    SkippedFrame,
    check_depth,
)
from csa_core.errors import CSAInputError

log = logging.getLogger(__name__)

RESERVED_FOLDERS = {"color", "depth", "pose", "intrinsic", "preview"}  # preview: colourised renders
LabelSpec = None | str | Sequence[str]


def frame_names(folder: Path, exts: tuple[str, ...] = imf.COLOR_EXTS) -> list[str]:
    """Frame names (file stems) of the images in ``folder`` (suffix in any case), sorted by
    frame index; a name with two images (``0.jpg`` and ``0.png``) is an error naming both."""
    found: dict[str, str] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in exts or p.name.startswith("."):
            continue
        if p.stem in found:
            raise CSAInputError(
                p, f"frame {p.stem!r} has two images ({found[p.stem]} and {p.name}); keep one"
            )
        found[p.stem] = p.name
    return sorted(found, key=lambda s: (0, int(s), s) if s.isdigit() else (1, 0, s))


def _find_image(folder: Path, name: str, exts: Iterable[str] = (".png",)) -> Path:
    """The image of frame ``name`` in ``folder`` with one of ``exts``, in lower or upper case
    (cameras write ``.JPG``); the first candidate when there is none (its reader then says it
    is missing), or an error when the frame's file there has another format (``0.tiff``)."""
    exts = tuple(exts)
    for ext in exts:
        for suffix in (ext, ext.upper()):
            p = folder / f"{name}{suffix}"
            if p.is_file():
                return p
    want = folder / f"{name}{exts[0]}"
    others = (
        sorted(p.name for p in folder.glob(f"{glob.escape(name)}.*")) if folder.is_dir() else []
    )
    if others:
        raise CSAInputError(
            want,
            f"file not found ({others[0]} is there, but this folder's images must be "
            f"{'/'.join(exts)})",
        )
    return want


def label_folders_of(root: Path) -> list[str]:
    """Names of the label folders in a scene folder (every non-reserved sub-folder)."""
    return sorted(
        p.name
        for p in root.iterdir()
        if p.is_dir() and p.name not in RESERVED_FOLDERS and not p.name.startswith(".")
    )


def _read_intrinsics(root: Path, which: str, width: int, height: int) -> Intrinsics:
    path = root / "intrinsic" / f"intrinsic_{which}.txt"
    return intrinsics_from_matrix(imf.read_matrix(path, ((3, 3), (4, 4))), width, height, path)


def _check_size(path: Path, img: np.ndarray, want: tuple[int, int], what: str) -> None:
    if (img.shape[1], img.shape[0]) != want:
        raise CSAInputError(
            path,
            f"size mismatch: {what} is {img.shape[1]}x{img.shape[0]}, expected {want[0]}x{want[1]} "
            f"like the other {what} images",
        )


def _read_pose(path: Path) -> np.ndarray:
    """A rigid camera-to-world pose; a non-finite one (lost tracking) is returned for skipping."""
    pose = imf.read_matrix(path, ((4, 4),))
    return check_pose(pose, path) if np.all(np.isfinite(pose)) else pose


def _resolve_labels(root: Path, labels: LabelSpec, label_map: Path | None) -> list[str]:
    present = label_folders_of(root)
    if labels is None:
        wanted = [NYU40_FOLDER] if NYU40_FOLDER in present else []
        if RAW_SCANNET_FOLDER in present and label_map is not None:
            wanted.append(RAW_SCANNET_FOLDER)
        return wanted
    if isinstance(labels, str):
        if labels == "all":
            return [n for n in present if n != RAW_SCANNET_FOLDER or label_map is not None]
        labels = [labels]
    for name in labels:
        if name not in present:
            raise CSAInputError(
                root / name,
                f"unknown label folder '{name}' (this scene has: {', '.join(present) or 'none'})",
            )
        if name == RAW_SCANNET_FOLDER and label_map is None:
            raise CSAInputError(
                root / name,
                "holds raw ScanNet ids; "
                "pass the scannetv2-labels.combined.tsv label map to read it",
            )
    return list(labels)


def read_scene(
    path: str | Path,
    size: tuple[int, int] | None = None,
    labels: LabelSpec = None,
    every: int = 1,
    label_map: str | Path | None = None,
    workers: int = 4,
) -> Scene:
    """Read a scene folder into memory at a working resolution.

    ``size`` is (width, height); by default the colour resolution. Colour is area-resampled,
    depth and labels nearest-neighbour; intrinsics follow per axis. ``labels``: ``None`` reads
    ``label-nyu40`` (and ``label-filt`` when ``label_map`` is given), ``"all"`` every label folder,
    or a list of folder names. Raw ``label-filt`` ids are mapped to NYU40 with ``label_map``
    (ScanNet's ``scannetv2-labels.combined.tsv``); without a ``label-nyu40`` folder the mapped
    labels are stored under ``label-nyu40``. ``every`` keeps every N-th frame. Frames whose pose
    is not finite are skipped and listed in ``Scene.skipped``.
    """
    root = Path(path)
    if not root.is_dir():
        raise CSAInputError(root, "scene folder not found")
    if every < 1:
        raise CSAInputError("--every", f"must be >= 1, got {every}")
    color_dir, depth_dir, pose_dir = root / "color", root / "depth", root / "pose"
    for d in (color_dir, pose_dir):
        if not d.is_dir():
            raise CSAInputError(d, "folder missing (a scene needs color/, pose/ and intrinsic/)")
    names = frame_names(color_dir)
    if not names:
        raise CSAInputError(color_dir, "no colour images (.jpg/.png)")
    names = names[::every]
    folders = _resolve_labels(root, labels, Path(label_map) if label_map is not None else None)
    lut = (
        load_raw_to_nyu40(label_map)
        if label_map is not None and RAW_SCANNET_FOLDER in folders
        else None
    )
    has_depth = depth_dir.is_dir()

    first = imf.read_color(_find_image(color_dir, names[0], imf.COLOR_EXTS))
    color_size = (first.shape[1], first.shape[0])
    color_cam = _read_intrinsics(root, "color", *color_size)
    work = color_cam.scaled(*size) if size is not None else color_cam
    if work.width < 1 or work.height < 1:
        raise CSAInputError("--size", f"working size must be positive, got {size}")
    depth_cam: Intrinsics | None = None
    depth_size: tuple[int, int] | None = None
    if has_depth:
        d0_path = _find_image(depth_dir, names[0])
        d0 = imf.read_depth_mm(d0_path)
        depth_size = (d0.shape[1], d0.shape[0])
        depth_txt = root / "intrinsic" / "intrinsic_depth.txt"
        if depth_txt.is_file():
            depth_cam = _read_intrinsics(root, "depth", *depth_size)
        else:
            hint = "; add intrinsic/intrinsic_depth.txt when depth comes from another camera"
            depth_cam = _colour_camera_at(d0_path, depth_size, color_cam, "depth is", hint)

    def load(name: str) -> Frame | SkippedFrame:
        pose_path = pose_dir / f"{name}.txt"
        pose = _read_pose(pose_path)
        if not np.all(np.isfinite(pose)):
            return SkippedFrame(name, f"{pose_path}: pose is not finite")
        cpath = _find_image(color_dir, name, imf.COLOR_EXTS)
        color = imf.read_color(cpath)
        _check_size(cpath, color, color_size, "colour")
        frame = Frame(name=name, color=resize_color(color, work.width, work.height), pose=pose)
        if has_depth:
            dpath = _find_image(depth_dir, name)
            mm = imf.read_depth_mm(dpath)
            _check_size(dpath, mm, depth_size, "depth")
            frame.depth = resample_nearest(mm, depth_cam, work).astype(np.float32) / 1000.0
        for folder in folders:
            lpath = _find_image(root / folder, name)
            raw = folder == RAW_SCANNET_FOLDER
            lab = imf.read_label_image(lpath, max_id=None if raw else 40)
            if raw:
                lab = lut[lab.astype(np.int64)]
            lab_cam = _colour_camera_at(
                lpath, (lab.shape[1], lab.shape[0]), color_cam, "labels are"
            )
            key = NYU40_FOLDER if raw and NYU40_FOLDER not in folders else folder
            frame.labels[key] = resample_nearest(lab, lab_cam, work)
        return frame

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        loaded = list(pool.map(load, names))
    frames = [f for f in loaded if isinstance(f, Frame)]
    skipped = [f for f in loaded if isinstance(f, SkippedFrame)]
    for s in skipped:
        log.warning("skipping frame %s: %s", s.name, s.reason)
    if not frames:
        raise CSAInputError(pose_dir, "no frame has a finite pose")
    if has_depth:
        check_depth(frames, depth_dir)
    return Scene(name=root.name, intrinsics=work, frames=frames, skipped=skipped, root=root)


def _colour_camera_at(
    path: Path, size: tuple[int, int], color_cam: Intrinsics, what: str, hint: str = ""
) -> Intrinsics:
    """The colour camera at another resolution ``size`` of the same aspect (within 1%): the camera
    of labels, and of depth without ``intrinsic_depth.txt``; ``what`` names the image in errors."""
    w, h = size
    if abs(w / h - color_cam.width / color_cam.height) > 0.01:
        raise CSAInputError(
            path,
            f"size mismatch: {what} {w}x{h}, colour is {color_cam.width}x{color_cam.height} "
            f"(aspect ratios differ{hint})",
        )
    return color_cam.scaled(w, h)


def read_label_folder(folder: str | Path) -> dict[str, np.ndarray]:
    """Every label map in a folder, keyed by frame name (uint8 NYU40 ids)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CSAInputError(folder, "label folder not found")
    return {
        name: imf.read_label_image(folder / f"{name}.png")
        for name in frame_names(folder, (".png",))
    }


def write_label_folder(
    dest: str | Path, labels: dict[str, np.ndarray], overwrite: bool = False
) -> Path:
    """Write ``{frame name: label map}`` as a label folder (uint8 PNGs), atomically."""
    dest = Path(dest)
    with atomic_dir(dest, overwrite=overwrite) as tmp:
        for name, lab in labels.items():
            imf.write_labels(tmp / f"{name}.png", lab)
    return dest


def write_scene(
    scene: Scene, dest: str | Path, overwrite: bool = False, color_ext: str = ".png"
) -> Path:
    """Write a scene in the scene-folder layout, atomically (all or nothing).

    Colour defaults to lossless PNG; depth is stored as uint16 millimetres (0 = missing);
    intrinsics as 4x4 ScanNet-style matrices for colour and (registered) depth.
    """
    dest = Path(dest)
    if not scene.frames:
        raise CSAInputError(dest, "refusing to write a scene without frames")
    K = np.eye(4)
    K[:3, :3] = scene.intrinsics.matrix()
    with atomic_dir(dest, overwrite=overwrite) as tmp:
        for sub in ("color", "pose", "intrinsic"):
            (tmp / sub).mkdir()
        imf.write_matrix(tmp / "intrinsic" / "intrinsic_color.txt", K)
        if any(f.depth is not None for f in scene.frames):
            (tmp / "depth").mkdir()
            imf.write_matrix(tmp / "intrinsic" / "intrinsic_depth.txt", K)
        for f in scene.frames:
            if (f.color.shape[1], f.color.shape[0]) != scene.size:
                raise CSAInputError(
                    f"frame {f.name}",
                    f"colour is {f.color.shape[1]}x{f.color.shape[0]}, scene is "
                    f"{scene.size[0]}x{scene.size[1]}",
                )
            imf.write_color(tmp / "color" / f"{f.name}{color_ext}", f.color)
            imf.write_matrix(tmp / "pose" / f"{f.name}.txt", f.pose)
            if f.depth is not None:
                imf.write_depth(tmp / "depth" / f"{f.name}.png", f.depth)
            for folder, lab in f.labels.items():
                (tmp / folder).mkdir(exist_ok=True)
                imf.write_labels(tmp / folder / f"{f.name}.png", lab)
    return dest
