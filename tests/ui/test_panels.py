"""The dashboard's picture helpers without a server: label maps computed once per frame,
failures not remembered, legends in NYU40 names and colours."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from csa_core.data.camera import Intrinsics
from csa_core.data.nyu40 import CLASS_NAMES, class_color
from server.services.nerfs import MAX_RENDER_PIXELS
from server.ui.panels import LabelMaps, PanelSource, draw_panel, legend


def test_a_label_map_asked_for_twice_at_once_is_made_once() -> None:
    maps = LabelMaps(size=2)
    calls: list[int] = []
    started, release = threading.Event(), threading.Event()

    def slow() -> np.ndarray:
        calls.append(1)
        started.set()
        release.wait(10)
        return np.full((2, 3), 7, np.uint8)

    results: list[np.ndarray] = []
    first = threading.Thread(target=lambda: results.append(maps.get(("a",), slow)))
    first.start()
    started.wait(10)
    second = threading.Thread(target=lambda: results.append(maps.get(("a",), slow)))
    second.start()
    release.set()
    first.join(10)
    second.join(10)
    assert len(calls) == 1 and len(results) == 2 and all((r == 7).all() for r in results)
    maps.get(("b",), lambda: np.zeros((1, 1), np.uint8))
    maps.get(("c",), lambda: np.zeros((1, 1), np.uint8))
    maps.get(("a",), slow)  # evicted (size 2): made again
    assert len(calls) == 2


def test_a_failure_is_raised_to_every_waiter_and_not_remembered() -> None:
    maps = LabelMaps()

    def broken() -> np.ndarray:
        raise RuntimeError("render failed")

    with pytest.raises(RuntimeError, match="render failed"):
        maps.get(("k",), broken)
    assert maps.get(("k",), lambda: np.ones((1, 1), np.uint8)).item() == 1


def test_legend_lists_present_classes_most_frequent_first() -> None:
    labels = np.array([[1, 1, 1, 5], [5, 40, 1, 1]], np.uint8)
    items = legend(labels)
    assert [i["id"] for i in items] == [1, 5, 40]
    assert [i["share"] for i in items] == [5 / 8, 2 / 8, 1 / 8]
    assert items[0]["name"] == CLASS_NAMES[1] == "wall"
    assert items[2]["color"] == "#{:02x}{:02x}{:02x}".format(*class_color(40))


def draw_pseudo_panel(tmp_path: Path, camera: dict) -> tuple[list[Intrinsics], np.ndarray]:
    """The pseudo-label panel of a black frame of ``camera``'s size, by a NeRF that renders
    class 5 everywhere: the cameras it was asked to render, and the panel (BGR)."""
    color = tmp_path / "color.png"
    assert cv2.imwrite(str(color), np.zeros((camera["height"], camera["width"], 3), np.uint8))
    asked: list[Intrinsics] = []

    class Store:
        def open_verified(self, sha: str) -> Path:
            return color

    class Nerfs:
        def render(self, nerf_id, files, pose, intrinsics: Intrinsics) -> dict[str, np.ndarray]:
            asked.append(intrinsics)
            return {"labels": np.full((intrinsics.height, intrinsics.width), 5, np.uint8)}

    files = {"nerf.safetensors": "n"}
    src = PanelSource("pseudo", "c", None, None, 1, files, np.eye(4).tolist(), camera)
    body = draw_panel(src, Store(), None, Nerfs(), LabelMaps())
    return asked, cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)


def test_a_pseudo_label_panel_of_a_large_frame_renders_within_the_render_limit(
    tmp_path: Path,
) -> None:
    """The render route refuses views of more than ``MAX_RENDER_PIXELS`` (a view holds its
    class scores for every pixel); the pseudo-label panel rendered the frame's whole camera, so
    a scene of 4096x4096 frames made every panel of it render 16 times that, gigabytes of
    scores. It renders the same camera scaled down to the limit and draws the labels at the
    frame's size."""
    w, h = 1600, 1000  # 1.6 million pixels
    camera = {"fx": 1200.0, "fy": 1100.0, "cx": 799.5, "cy": 499.5, "width": w, "height": h}
    (intr,), panel = draw_pseudo_panel(tmp_path, camera)
    assert intr.width * intr.height <= MAX_RENDER_PIXELS
    assert intr == Intrinsics.from_dict(camera).scaled(intr.width, intr.height)
    assert intr.width / intr.height == pytest.approx(w / h, rel=0.01)
    assert panel.shape == (h, w, 3) and (panel[..., ::-1] == class_color(5)).all()


def test_a_pseudo_label_panel_within_the_limit_renders_the_frames_camera(tmp_path: Path) -> None:
    camera = {"fx": 30.0, "fy": 30.0, "cx": 19.5, "cy": 14.5, "width": 40, "height": 30}
    asked, panel = draw_pseudo_panel(tmp_path, camera)
    assert asked == [Intrinsics.from_dict(camera)] and panel.shape == (30, 40, 3)
