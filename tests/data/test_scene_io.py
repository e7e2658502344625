"""The scene-folder reader and writer: round trips, ScanNet quirks and bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from csa_core.data import image_files as imf
from csa_core.data.camera import Intrinsics
from csa_core.data.scene import split_point
from csa_core.data.scene_io import read_label_folder, read_scene, write_label_folder, write_scene
from csa_core.errors import CSAInputError
from tests.tiny_scenes import make_random_scene


def test_round_trip_is_exact(tmp_path, random_scene):
    out = write_scene(random_scene, tmp_path / "s")
    back = read_scene(out, labels="all")
    assert [f.name for f in back.frames] == ["0", "10", "20", "30", "40"]
    assert back.intrinsics == random_scene.intrinsics
    for a, b in zip(random_scene.frames, back.frames, strict=True):
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.labels["label-nyu40"], b.labels["label-nyu40"])
        assert b.depth.dtype == np.float32 and b.labels["label-nyu40"].dtype == np.uint8


def test_frames_sort_numerically_not_lexically(tmp_path):
    scene = make_random_scene(n=12)
    for i, f in enumerate(scene.frames):
        f.name = str(i)
    back = read_scene(write_scene(scene, tmp_path / "s"))
    assert [f.name for f in back.frames] == [str(i) for i in range(12)]


def test_split_is_first_80_percent(tmp_path):
    scene = make_random_scene(n=10)
    back = read_scene(write_scene(scene, tmp_path / "s"))
    assert [f.name for f in back.train_frames] == [str(i * 10) for i in range(8)]
    assert [f.name for f in back.val_frames] == ["80", "90"]
    assert split_point(100) == 80 and split_point(2) == 1 and split_point(1) == 1


def test_every_nth_then_split(tmp_path):
    scene = make_random_scene(n=10)
    back = read_scene(write_scene(scene, tmp_path / "s"), every=3)
    assert [f.name for f in back.frames] == ["0", "30", "60", "90"]
    assert back.num_train == 3


def test_resize_scales_intrinsics_and_uses_nearest_for_depth_and_labels(tmp_path):
    scene = make_random_scene(n=2, size=(32, 24))
    back = read_scene(write_scene(scene, tmp_path / "s"), size=(16, 12), labels="all")
    k = back.intrinsics
    assert (k.width, k.height) == (16, 12)
    assert k.fx == pytest.approx(15.0) and k.fy == pytest.approx(15.5)
    # pixel (i, j) at half size covers source pixels 2i..2i+1; nearest picks one of them
    src, dst = scene.frames[0], back.frames[0]
    for name, a, b in (
        ("depth", src.depth, dst.depth),
        ("labels", src.labels["label-nyu40"], dst.labels["label-nyu40"]),
    ):
        blocks = a.reshape(12, 2, 16, 2).transpose(0, 2, 1, 3).reshape(12, 16, 4)
        assert np.all((blocks == b[..., None]).any(-1)), name
    assert dst.color.shape == (12, 16, 3)


def _scannet_like(tmp_path: Path) -> Path:
    """Colour 64x48 and depth 32x24 with a different camera, as in ScanNet exports."""
    root = tmp_path / "scene0000_00"
    for d in ("color", "depth", "pose", "intrinsic", "label-filt"):
        (root / d).mkdir(parents=True)
    Kc = np.array([[60.0, 0, 31.5, 0], [0, 60.0, 23.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    Kd = np.array([[28.0, 0, 16.0, 0], [0, 28.0, 11.0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", Kc)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", Kd)
    u, v = np.meshgrid(np.arange(32), np.arange(24))
    depth_mm = (1000 + 10 * u + 1000 * v).astype(np.uint16)  # encodes the depth pixel it came from
    rng = np.random.default_rng(0)
    for i in range(5):
        cv2.imwrite(
            str(root / "color" / f"{i}.jpg"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
        )
        cv2.imwrite(str(root / "depth" / f"{i}.png"), depth_mm)
        raw = np.full((48, 64), 7, np.uint16)
        raw[:, 32:] = 1164  # a raw id that maps to NYU40 via the tsv
        raw[:5] = 999  # not in the tsv -> unknown
        cv2.imwrite(str(root / "label-filt" / f"{i}.png"), raw)
        pose = np.eye(4)
        pose[0, 3] = i
        if i == 2:
            pose[:] = -np.inf
        np.savetxt(root / "pose" / f"{i}.txt", pose)
    (tmp_path / "labels.tsv").write_text(
        "id\traw_category\tcategory\tcount\tnyu40id\tnyu40class\n7\tchair\tchair\t1\t5\tchair\n1164\tbed\tbed\t1\t4\tbed\n"
    )
    return root


def test_scannet_quirks(tmp_path):
    root = _scannet_like(tmp_path)
    scene = read_scene(root, size=(32, 24), label_map=tmp_path / "labels.tsv")
    assert [f.name for f in scene.frames] == ["0", "1", "3", "4"]
    assert [s.name for s in scene.skipped] == ["2"] and "not finite" in scene.skipped[0].reason
    k = scene.intrinsics
    assert (k.width, k.height, k.fx) == (32, 24, 30.0)
    # depth comes from the depth camera: working pixel (u, v) sees depth pixel
    # u_d = 28/30 (u - cx_w) + 16, v_d = 28/30 (v - cy_w) + 11
    d = scene.frames[0].depth
    for u, v in ((5, 5), (20, 12), (16, 11)):
        ud = round(28 / 30 * (u - k.cx) + 16)
        vd = round(28 / 30 * (v - k.cy) + 11)
        assert d[v, u] == pytest.approx((1000 + 10 * ud + 1000 * vd) / 1000.0)
    lab = scene.frames[0].labels["label-nyu40"]
    assert set(np.unique(lab[5:, :14])) == {5} and set(np.unique(lab[5:, 18:])) == {4}
    assert np.all(lab[:2] == 0)


def test_label_filt_needs_label_map(tmp_path):
    root = _scannet_like(tmp_path)
    assert "label-nyu40" not in read_scene(root).label_folders  # skipped silently by default
    with pytest.raises(CSAInputError, match="scannetv2-labels.combined.tsv"):
        read_scene(root, labels=["label-filt"])


def test_label_map_missing_columns(tmp_path):
    root = _scannet_like(tmp_path)
    (tmp_path / "bad.tsv").write_text("raw\tnyu\n1\t2\n")
    with pytest.raises(CSAInputError, match=r"bad.tsv: missing column\(s\) id, nyu40id"):
        read_scene(root, label_map=tmp_path / "bad.tsv")


def test_named_label_folder_and_unknown_folder(tmp_path, random_scene):
    for f in random_scene.frames:
        f.labels["pred-v1"] = f.labels["label-nyu40"] // 2
    root = write_scene(random_scene, tmp_path / "s")
    scene = read_scene(root, labels=["pred-v1"])
    assert scene.label_folders == ["pred-v1"]
    with pytest.raises(
        CSAInputError, match=r"unknown label folder 'nope' \(this scene has: label-nyu40, pred-v1\)"
    ):
        read_scene(root, labels=["nope"])


def test_missing_depth_is_kept_missing(tmp_path, random_scene):
    root = write_scene(random_scene, tmp_path / "s")
    back = read_scene(root)
    src = random_scene.frames[1]
    assert np.array_equal(back.frames[1].depth_mask, src.depth > 0)
    shutil.rmtree(root / "depth")
    assert read_scene(root).frames[0].depth is None


def _depth_of_another_aspect(root: Path) -> None:
    """Square depth images and no depth intrinsics: the colour camera cannot be scaled to them."""
    (root / "intrinsic" / "intrinsic_depth.txt").unlink()
    for p in (root / "depth").iterdir():
        cv2.imwrite(str(p), np.full((32, 32), 1500, np.uint16))


def _depth_in_metres(root: Path) -> None:
    """Depth PNGs holding whole metres instead of millimetres."""
    for p in (root / "depth").iterdir():
        mm = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), np.round(mm / 1000.0).astype(np.uint16))


@pytest.mark.parametrize(
    ("break_it", "pattern"),
    [
        (
            lambda r: (r / "color" / "10.png").write_bytes(b"not an image"),
            r"color/10.png: cannot decode image",
        ),
        (
            lambda r: cv2.imwrite(str(r / "color" / "20.png"), np.zeros((5, 5, 3), np.uint8)),
            r"color/20.png: size mismatch",
        ),
        (
            lambda r: cv2.imwrite(str(r / "depth" / "30.png"), np.zeros((24, 32), np.uint8)),
            r"depth/30.png: depth must be a single-channel uint16",
        ),
        (lambda r: (r / "pose" / "40.txt").unlink(), r"pose/40.txt: file not found"),
        (
            lambda r: (r / "pose" / "0.txt").write_text("1 0 0\n0 1 0\n"),
            r"pose/0.txt: expected a 4x4 matrix, got 2x3",
        ),
        (
            lambda r: np.savetxt(r / "pose" / "10.txt", np.diag([5.0, 5.0, 5.0, 1.0])),
            r"pose/10.txt: rotation part is not orthonormal .* 24 > 0.001",
        ),
        (
            lambda r: np.savetxt(r / "pose" / "20.txt", np.diag([1.0, 1.0, -1.0, 1.0])),
            r"pose/20.txt: rotation part has determinant -1",
        ),
        (
            lambda r: np.savetxt(
                r / "pose" / "30.txt", np.r_[np.c_[np.eye(3), [2e4, 0, 0]], [[0, 0, 0, 1]]]
            ),
            r"pose/30.txt: translation is 2e\+04 m from the origin",
        ),
        (
            lambda r: (r / "intrinsic" / "intrinsic_color.txt").write_text(
                "0 0 16\n0 30 12\n0 0 1\n"
            ),
            r"intrinsic_color.txt: focal lengths must be positive, fx is 0",
        ),
        (
            lambda r: (r / "intrinsic" / "intrinsic_color.txt").write_text(
                "30 0 900\n0 30 12\n0 0 1\n"
            ),
            r"intrinsic_color.txt: principal point cx = 900 px",
        ),
        (
            lambda r: (r / "intrinsic" / "intrinsic_color.txt").unlink(),
            r"intrinsic_color.txt: file not found",
        ),
        (
            lambda r: cv2.imwrite(
                str(r / "label-nyu40" / "0.png"), np.full((24, 32), 41, np.uint8)
            ),
            r"label-nyu40/0.png: label id 41 is out of range",
        ),
        (lambda r: shutil.rmtree(r / "pose"), r"pose: folder missing"),
        # Intrinsics of twice the image size (images resized after calibration).
        (
            lambda r: (r / "intrinsic" / "intrinsic_color.txt").write_text(
                "60 0 31.5\n0 62 23.5\n0 0 1\n"
            ),
            r"intrinsic_color.txt: principal point cx = 31.5 px "
            r"is far from the centre \(15.5\) of the 32x24 image",
        ),
        (
            lambda r: shutil.copy(r / "color" / "20.png", r / "color" / "20.jpg"),
            r"color/20.png: frame '20' has two images \(20.jpg and 20.png\)",
        ),
        (
            _depth_of_another_aspect,
            r"depth/0.png: size mismatch: depth is 32x32, colour is 32x24 "
            r"\(aspect ratios differ; add intrinsic/intrinsic_depth.txt",
        ),
        (
            _depth_in_metres,
            r"depth: typical measured depth is 0.00\d+ m, "
            r"outside 0.1..100 m: depth in another unit",
        ),
        (
            lambda r: (r / "depth" / "30.png").rename(r / "depth" / "30.tiff"),
            r"depth/30.png: file not found "
            r"\(30.tiff is there, but this folder's images must be .png\)",
        ),
        (lambda r: (r / "pose" / "20.txt").write_text("\n"), r"pose/20.txt: file is empty"),
    ],
)
def test_bad_input_names_the_file(tmp_path, random_scene, break_it, pattern):
    root = write_scene(random_scene, tmp_path / "s")
    break_it(root)
    with pytest.raises(CSAInputError, match=pattern):
        read_scene(root, labels="all")


def test_write_is_all_or_nothing(tmp_path, random_scene):
    random_scene.frames[3].color = random_scene.frames[3].color[:5]
    with pytest.raises(CSAInputError, match="frame 30"):
        write_scene(random_scene, tmp_path / "s")
    assert list(tmp_path.iterdir()) == []


def test_write_refuses_to_overwrite(tmp_path, random_scene):
    root = write_scene(random_scene, tmp_path / "s")
    with pytest.raises(CSAInputError, match="already exists"):
        write_scene(random_scene, root)
    write_scene(make_random_scene(n=2), root, overwrite=True)
    assert len(read_scene(root)) == 2


def test_label_folder_round_trip(tmp_path):
    labs = {"3": np.arange(12, dtype=np.uint8).reshape(3, 4), "1": np.zeros((3, 4), np.uint8)}
    back = read_label_folder(write_label_folder(tmp_path / "pred", labs))
    assert list(back) == ["1", "3"]
    np.testing.assert_array_equal(back["3"], labs["3"])


def test_intrinsics_scaling_keeps_pixel_centres():
    k = Intrinsics(100.0, 100.0, 63.5, 47.5, 128, 96)
    half = k.scaled(64, 48)
    assert (half.cx, half.cy) == (31.5, 23.5)  # image centre stays the image centre
    assert imf.depth_to_mm(np.array([0.0, 1.2344, np.nan, 70.0])).tolist() == [0, 1234, 0, 0]


def test_upper_case_suffixes_are_read(tmp_path, random_scene):
    """Cameras write 0.JPG: the frame is found, not reported missing."""
    root = write_scene(random_scene, tmp_path / "s")
    for sub in ("color", "depth", "label-nyu40"):
        for p in (root / sub).iterdir():
            p.rename(p.with_suffix(".PNG"))
    back = read_scene(root, labels="all")
    assert [f.name for f in back.frames] == [f.name for f in random_scene.frames]
    for a, b in zip(random_scene.frames, back.frames, strict=True):
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.labels["label-nyu40"], b.labels["label-nyu40"])


def test_depth_65535_is_no_measurement(tmp_path, random_scene):
    """The uint16 maximum is a sensor's "no measurement", not a surface 65.5 m away (which
    would stretch the NeRF's scene box over the whole range)."""
    root = write_scene(random_scene, tmp_path / "s")
    mm = cv2.imread(str(root / "depth" / "10.png"), cv2.IMREAD_UNCHANGED)
    mm[:, :5] = 65535
    cv2.imwrite(str(root / "depth" / "10.png"), mm)
    depth = read_scene(root).frames[1].depth
    assert np.all(depth[:, :5] == 0)
    np.testing.assert_array_equal(depth[:, 5:], random_scene.frames[1].depth[:, 5:])
