"""The ``csa`` command line: commands work, and bad input gives one line, exit 2, no output."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path

import cv2
import numpy as np
import pytest

from csa_core.cli import main as cli_main
from csa_core.cli.main import GROUPS, PLUGIN_GROUP, build_parser, main
from csa_core.data.scene_io import write_label_folder, write_scene
from tests.tiny_scenes import make_random_scene


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_building_the_parser_imports_neither_torch_nor_opencv_nor_the_web_stack():
    heavy = ("torch", "cv2", "fastapi", "uvicorn", "sqlalchemy", "pydantic_settings")
    code = (
        "import sys; from csa_core.cli.main import build_parser; build_parser(); "
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"
    assert proc.stderr == ""  # every declared plugin loaded, no note


def test_serve_comes_from_the_services_entry_point():
    declared = {ep.name: ep.value for ep in entry_points(group=PLUGIN_GROUP)}
    service = ("backup", "doctor", "keys", "restore", "serve")
    assert declared == {name: f"server.cli:register_{name}" for name in service}
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == [*GROUPS, *service]
    args = build_parser().parse_args(["serve", "--port", "8123", "--no-worker", "--data-dir", "d"])
    assert (args.port, args.no_worker, args.host, args.data_dir, args.func.__module__) == (
        8123,
        True,
        "127.0.0.1",
        Path("d"),
        "server.cli",
    )


def test_serve_help_through_the_console_entry(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["serve", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: csa serve") and "--database-url" in out


def register_hello(sub: argparse._SubParsersAction) -> None:
    """A plugin command for the tests below: ``csa hello NAME`` prints a greeting."""
    p = sub.add_parser("hello", help="greet")
    p.add_argument("name")
    p.set_defaults(func=lambda args: print(f"hello {args.name}"))


def test_plugins_add_commands_and_a_missing_one_is_a_note(monkeypatch, capsys):
    plugins = [
        EntryPoint("hello", "tests.test_cli:register_hello", PLUGIN_GROUP),
        EntryPoint("hello", "tests.test_cli:register_hello", PLUGIN_GROUP),  # the same one twice
        EntryPoint("gone", "no_such_package.cli:register", PLUGIN_GROUP),
        EntryPoint("data", "tests.test_cli:register_hello", PLUGIN_GROUP),  # a built-in name
    ]
    monkeypatch.setattr(
        cli_main, "entry_points", lambda group: [ep for ep in plugins if ep.group == group]
    )
    code, out, err = run(capsys, "hello", "world")
    assert (code, out) == (0, "hello world\n")
    notes = err.splitlines()
    assert len(notes) == 2
    assert notes[0].startswith(
        "csa: note: command 'data' from tests.test_cli:register_hello ignored"
    )
    assert notes[1].startswith(
        "csa: note: command 'gone' unavailable (no_such_package.cli:register)"
    )


def test_service_flags_override_the_environment(monkeypatch, tmp_path):
    pytest.importorskip("pydantic_settings")
    from server.cli import settings_from_args

    monkeypatch.setenv("CSA_DATA_DIR", str(tmp_path / "from-env"))
    monkeypatch.setenv("CSA_DATABASE_URL", "sqlite:///env.db")
    args = build_parser().parse_args(["serve", "--data-dir", str(tmp_path / "flag")])
    settings = settings_from_args(args, embedded_worker=False)
    assert (settings.data_dir, settings.database_url, settings.embedded_worker) == (
        tmp_path / "flag",
        "sqlite:///env.db",
        False,
    )
    settings = settings_from_args(build_parser().parse_args(["serve"]))
    assert (settings.data_dir, settings.database_url) == (tmp_path / "from-env", "sqlite:///env.db")


def test_import_7scenes_camera_choices_are_the_importers():
    from csa_core.cli.data import CAMERA_CHOICES
    from csa_core.data.sevenscenes import CAMERAS

    assert CAMERA_CHOICES == CAMERAS


def test_import_7scenes_and_info(tmp_path, capsys, seven_scenes_dir):
    code, out, _ = run(
        capsys,
        "data",
        "import-7scenes",
        str(seven_scenes_dir),
        str(tmp_path / "k"),
        "--every",
        "5",
        "--size",
        "80x60",
    )
    assert code == 0 and "20 frames at 80x60" in out
    assert sorted(p.name for p in (tmp_path / "k").iterdir()) == [
        "color",
        "depth",
        "intrinsic",
        "pose",
    ]
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
    code, out, _ = run(
        capsys,
        "eval",
        "miou",
        str(tmp_path / "pred"),
        str(tmp_path / "gt"),
        "--json",
        str(tmp_path / "m.json"),
    )
    assert code == 0
    # class 1: tp 2, fn 1, fp 0 -> 2/3; class 2: tp 3, fp 1 -> 3/4; class 3: 1
    summary = json.loads((tmp_path / "m.json").read_text())
    assert summary["miou"] == pytest.approx((2 / 3 + 3 / 4 + 1) / 3)
    assert "mIoU" in out
    # a render of some views against the scene's whole label folder
    (tmp_path / "pred" / "1.png").unlink()
    code, _, err = run(capsys, "eval", "miou", str(tmp_path / "pred"), str(tmp_path / "gt"))
    assert code != 0 and "no prediction for 1 ground-truth frame(s): 1" in err
    args = ["eval", "miou", "--predicted-only", str(tmp_path / "pred"), str(tmp_path / "gt")]
    code, out, _ = run(capsys, *args, "--json", str(tmp_path / "m0.json"))
    assert code == 0
    # frame 0 alone: class 1 tp 1, fn 1 -> 1/2; class 2 tp 2, fp 1 -> 2/3
    summary = json.loads((tmp_path / "m0.json").read_text())
    assert summary["num_frames"] == 1
    assert summary["miou"] == pytest.approx((1 / 2 + 2 / 3) / 2)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["data", "import-7scenes", "{tmp}/empty", "{tmp}/out"],
            "empty: no frame-XXXXXX.color.jpg",
        ),
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
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "csa_core.cli.main",
            "data",
            "preview",
            str(root),
            "--out",
            str(tmp_path / "p"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().endswith(
        "color/10.png: cannot decode image (corrupt or not an image)"
    )
    assert not (tmp_path / "p").exists()


def test_bad_size_flag_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["data", "synth", "x", "--size", "big"])
    assert exc.value.code == 2
    assert "--size: expected WIDTHxHEIGHT" in capsys.readouterr().err
