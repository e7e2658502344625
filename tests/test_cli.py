"""The ``csa`` command line: commands work, and bad input gives one line, exit 2, no output."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from csa_core.cli.main import main
from csa_core.data.scene_io import write_label_folder, write_scene
from tests.tiny_scenes import make_random_scene


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_building_the_parser_imports_neither_torch_nor_opencv():
    code = "import sys; from csa_core.cli.main import build_parser; build_parser(); print(sorted(m for m in ('torch', 'cv2') if m in sys.modules))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_import_7scenes_camera_choices_are_the_importers():
    from csa_core.cli.data import CAMERA_CHOICES
    from csa_core.data.sevenscenes import CAMERAS

    assert CAMERA_CHOICES == CAMERAS


def test_import_7scenes_and_info(tmp_path, capsys, seven_scenes_dir):
    code, out, _ = run(capsys, "data", "import-7scenes", str(seven_scenes_dir), str(tmp_path / "k"), "--every", "5", "--size", "80x60")
    assert code == 0 and "20 frames at 80x60" in out
    assert sorted(p.name for p in (tmp_path / "k").iterdir()) == ["color", "depth", "intrinsic", "pose"]
    code, out, _ = run(capsys, "data", "info", str(tmp_path / "k"))
    assert code == 0 and "20 (16 train / 4 val)" in out and "% measured" in out


def test_preview_writes_one_png_per_frame(tmp_path, capsys):
    root = write_scene(make_random_scene(n=4), tmp_path / "s")
    code, out, _ = run(capsys, "data", "preview", str(root), "--out", str(tmp_path / "prev"))
    assert code == 0
    pngs = sorted(p.name for p in (tmp_path / "prev").iterdir())
    assert pngs == ["0.png", "10.png", "20.png", "30.png"]
    img = cv2.imread(str(tmp_path / "prev" / "0.png"))
    assert img.shape[0] >= 24 and img.shape[1] >= 3 * 32  # colour | labels | overlay side by side


def test_eval_miou_command(tmp_path, capsys):
    gt = {"0": np.array([[1, 1], [2, 2]], np.uint8), "1": np.array([[2, 0], [1, 3]], np.uint8)}
    pred = {"0": np.array([[1, 2], [2, 2]], np.uint8), "1": np.array([[2, 5], [1, 3]], np.uint8)}
    write_label_folder(tmp_path / "gt", gt)
    write_label_folder(tmp_path / "pred", pred)
    code, out, _ = run(capsys, "eval", "miou", str(tmp_path / "pred"), str(tmp_path / "gt"), "--json", str(tmp_path / "m.json"))
    assert code == 0
    # class 1: tp 2, fn 1, fp 0 -> 2/3; class 2: tp 3, fp 1 -> 3/4; class 3: 1
    summary = json.loads((tmp_path / "m.json").read_text())
    assert summary["miou"] == pytest.approx((2 / 3 + 3 / 4 + 1) / 3)
    assert "mIoU" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["data", "import-7scenes", "{tmp}/empty", "{tmp}/out"], "empty: no frame-XXXXXX.color.jpg"),
        (["data", "info", "{tmp}/nothing"], "nothing: scene folder not found"),
        (["data", "synth", "{tmp}/out", "--family", "no-such-family"], "no-such-family"),
        (["eval", "miou", "{tmp}/empty", "{tmp}/nothing"], "nothing"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_no_output(tmp_path, capsys, argv, message):
    (tmp_path / "empty").mkdir()
    code, out, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert code == 2
    assert err.startswith("csa: error: ") and err.count("\n") == 1 and message in err
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["empty"]  # no temporary left behind


def test_console_script_prints_no_traceback(tmp_path):
    root = write_scene(make_random_scene(n=3), tmp_path / "s")
    (root / "color" / "10.png").write_bytes(b"\x89PNG broken")
    proc = subprocess.run([sys.executable, "-m", "csa_core.cli.main", "data", "preview", str(root), "--out", str(tmp_path / "p")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().endswith("color/10.png: cannot decode image (corrupt or not an image)")
    assert not (tmp_path / "p").exists()


def test_bad_size_flag_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["data", "synth", "x", "--size", "big"])
    assert exc.value.code == 2
    assert "--size: expected WIDTHxHEIGHT" in capsys.readouterr().err
