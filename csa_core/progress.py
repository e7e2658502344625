"""The one progress-callback convention of the core's long loops.

Every long-running function (``train_segmentation``, ``pretrain``, ``fit_semantic_nerf``,
``make_pseudo_labels``, ``finetune_on_labels``, ``adapt_one_step``) takes an optional keyword
``on_progress`` and calls ``on_progress(message, fraction)`` as it goes: ``message`` is a
short status line ("epoch 3/12  loss 0.412"), ``fraction`` the share of *that call's* work
done, in [0, 1] and never decreasing. A caller (the service's jobs) reports it and may
raise from it to stop the loop, e.g. on a cancel: the exception propagates unchanged and
nothing is written after it. Without a callback nothing changes.
"""

from __future__ import annotations

from collections.abc import Callable

ProgressCallback = Callable[[str, float], None]


def notify(on_progress: ProgressCallback | None, message: str, fraction: float) -> None:
    """Call ``on_progress`` if there is one (so loops need no ``None`` checks of their own)."""
    if on_progress is not None:
        on_progress(message, fraction)


def sub_progress(
    on_progress: ProgressCallback | None, start: float, end: float
) -> ProgressCallback | None:
    """A callback for one phase of a longer call: its [0, 1] is mapped onto [start, end] of
    ``on_progress`` (``None`` stays ``None``)."""
    if on_progress is None:
        return None

    def report(message: str, fraction: float) -> None:
        on_progress(message, start + (end - start) * min(max(fraction, 0.0), 1.0))

    return report
