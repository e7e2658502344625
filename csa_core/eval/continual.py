"""Continual-learning scores over a sequence of scenes (docs/method.md, "Protocols and metrics").

``R[i, j]`` is the score (e.g. mIoU) on scene ``j`` after adapting to scenes ``0..i``, and
``b[j]`` the pre-trained model's score on scene ``j``. The results are in the units of ``R``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Matrix = Sequence[Sequence[float]] | np.ndarray


def _as_float_array(values: object, name: str) -> np.ndarray:
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"continual_metrics: {name} is not a numeric array ({exc})") from None


def _nonfinite_needed(scores: np.ndarray, base: np.ndarray) -> list[str]:
    """Names of the entries the metrics read (R[i, j] with j <= i + 1, all of b) that are not
    finite."""
    steps = len(base)
    needed = [
        (f"R[{i}, {j}]", scores[i, j]) for i in range(steps) for j in range(min(i + 2, steps))
    ]
    needed += [(f"b[{j}]", base[j]) for j in range(steps)]
    return [name for name, value in needed if not np.isfinite(value)]


def continual_metrics(R: Matrix, b: Sequence[float] | np.ndarray) -> dict[str, float]:
    """ACC, A, FWT and BWT of a T x T score matrix ``R`` against pre-trained scores ``b``.

    - ``acc``: mean_j R[T-1, j], the final score averaged over all scenes.
    - ``a``: mean of R[i, j] over i >= j, the score on every scene seen so far, over time.
    - ``fwt``: mean_{j>=1} (R[j-1, j] - b[j]), gain on a scene before adapting to it.
    - ``bwt``: mean_{j<T-1} (R[T-1, j] - R[j, j]), change on a scene after moving on
      (negative = forgetting).

    The lower triangle (diagonal included), the first superdiagonal R[j-1, j] and ``b`` must be
    finite; the rest of the upper triangle is unused and may be NaN. With T = 1 there are no
    terms for FWT and BWT, so both are NaN.
    """
    scores = _as_float_array(R, "R")
    base = _as_float_array(b, "b")
    if scores.ndim != 2 or scores.shape[0] != scores.shape[1] or scores.shape[0] == 0:
        raise ValueError(
            f"continual_metrics: R must be a non-empty square matrix, got {scores.shape}"
        )
    steps = scores.shape[0]
    if base.shape != (steps,):
        raise ValueError(
            f"continual_metrics: b must have {steps} entries (one per scene), got shape "
            f"{base.shape}"
        )

    bad = _nonfinite_needed(scores, base)
    if bad:
        shown = ", ".join(bad[:6]) + (", ..." if len(bad) > 6 else "")
        raise ValueError(
            f"continual_metrics: {shown} not finite (needed: R[i, j] for j <= i + 1, and all of b)"
        )

    nan = float("nan")
    last = scores[-1]
    before = np.diagonal(scores, offset=1)  # R[j-1, j] for j = 1..T-1
    return {
        "acc": float(last.mean()),
        "a": float(scores[np.tril_indices(steps)].mean()),
        "fwt": float((before - base[1:]).mean()) if steps > 1 else nan,
        "bwt": float((last[:-1] - np.diagonal(scores)[:-1]).mean()) if steps > 1 else nan,
    }


def previous_row(R: np.ndarray) -> np.ndarray:
    """Mean of R[i, j] over j < i for every step i (the paper's "Previous" row; NaN at step 0:
    nothing seen before)."""
    return np.array([R[i, :i].mean() if i else np.nan for i in range(R.shape[0])])
