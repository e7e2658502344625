"""Continual-learning metrics on a score matrix worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from csa_core.eval import continual_metrics

NAN = float("nan")
# R[i][j]: score on scene j after step i. R[0][2] is never read, so it may be missing.
R = [
    [50.0, 20.0, NAN],
    [45.0, 60.0, 30.0],
    [40.0, 55.0, 70.0],
]
B = [30.0, 25.0, 35.0]


def test_hand_computed_metrics():
    m = continual_metrics(R, B)
    assert set(m) == {"acc", "a", "fwt", "bwt"}
    assert m["acc"] == pytest.approx((40 + 55 + 70) / 3)  # last row
    assert m["a"] == pytest.approx((50 + 45 + 60 + 40 + 55 + 70) / 6)  # i >= j
    assert m["fwt"] == pytest.approx(((20 - 25) + (30 - 35)) / 2)  # R[j-1, j] - b[j]
    assert m["bwt"] == pytest.approx(((40 - 50) + (55 - 60)) / 2)  # R[T-1, j] - R[j, j]


def test_accepts_arrays_and_returns_plain_floats():
    m = continual_metrics(np.array(R), np.array(B))
    assert all(type(v) is float for v in m.values())
    assert m["bwt"] == pytest.approx(-7.5)


def test_single_scene_has_no_transfer_terms():
    m = continual_metrics([[0.4]], [0.3])
    assert m["acc"] == pytest.approx(0.4)
    assert m["a"] == pytest.approx(0.4)
    assert math.isnan(m["fwt"]) and math.isnan(m["bwt"])


def test_no_forgetting_and_no_transfer():
    same = [[0.5, 0.2], [0.5, 0.7]]
    m = continual_metrics(same, [0.1, 0.2])
    assert m["bwt"] == 0.0
    assert m["fwt"] == pytest.approx(0.0)


@pytest.mark.parametrize(
    ("scores", "base", "match"),
    [
        ([[1.0, 2.0]], [1.0], "square"),
        ([], [], "square"),
        ([[1.0, 2.0], [3.0]], [1.0, 2.0], "numeric"),
        (R, [1.0, 2.0], "3 entries"),
        ([[50.0, 20.0, NAN], [45.0, 60.0, 30.0], [NAN, 55.0, 70.0]], B, r"R\[2, 0\]"),
        ([[50.0, NAN, NAN], [45.0, 60.0, 30.0], [40.0, 55.0, 70.0]], B, r"R\[0, 1\]"),
        (R, [30.0, math.inf, 35.0], r"b\[1\]"),
    ],
)
def test_rejects_bad_input(scores, base, match):
    with pytest.raises(ValueError, match=match):
        continual_metrics(scores, base)
