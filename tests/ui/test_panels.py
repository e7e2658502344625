"""The dashboard's picture helpers without a server: label maps computed once per frame,
failures not remembered, legends in NYU40 names and colours."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from csa_core.data.nyu40 import CLASS_NAMES, class_color
from server.ui.panels import LabelMaps, legend


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
