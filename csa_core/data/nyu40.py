"""The NYU40 label set used everywhere inside CSA (0 = unknown / ignore), with its colours."""

from __future__ import annotations

import numpy as np

NUM_CLASSES = 40  # NYU40 ids 1..40; networks predict 40 channels for ids 1..40
UNKNOWN = 0

# Index = NYU40 id. Names as in ScanNet's scannetv2-labels.combined.tsv (nyu40class column).
CLASS_NAMES: tuple[str, ...] = (
    "unknown",
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "blinds", "desk", "shelves", "curtain", "dresser", "pillow", "mirror",
    "floor mat", "clothes", "ceiling", "books", "refrigerator", "television", "paper", "towel",
    "shower curtain", "box", "whiteboard", "person", "night stand", "toilet", "sink", "lamp",
    "bathtub", "bag", "otherstructure", "otherfurniture", "otherprop",
)  # fmt: skip
assert len(CLASS_NAMES) == NUM_CLASSES + 1

# Index = NYU40 id, RGB. The colour map of the ScanNet benchmark (and of most NYU40 figures),
# so previews read the same as the papers; unknown is black.
_PALETTE_RGB: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # unknown
    (174, 199, 232), (152, 223, 138), (31, 119, 180), (255, 187, 120), (188, 189, 34),
    (140, 86, 75), (255, 152, 150), (214, 39, 40), (197, 176, 213), (148, 103, 189),
    (196, 156, 148), (23, 190, 207), (178, 76, 76), (247, 182, 210), (66, 188, 102),
    (219, 219, 141), (140, 57, 197), (202, 185, 52), (51, 176, 203), (200, 54, 131),
    (92, 193, 61), (78, 71, 183), (172, 114, 82), (255, 127, 14), (91, 163, 138),
    (153, 98, 156), (140, 153, 101), (158, 218, 229), (100, 125, 154), (178, 127, 135),
    (120, 185, 128), (146, 111, 194), (44, 160, 44), (112, 128, 144), (96, 207, 209),
    (227, 119, 194), (213, 92, 176), (94, 106, 211), (82, 84, 163), (100, 85, 144),
)  # fmt: skip

PALETTE: np.ndarray = np.array(_PALETTE_RGB, dtype=np.uint8)
"""(41, 3) uint8 RGB colour of each NYU40 id (row = id); read-only."""
PALETTE.flags.writeable = False
assert PALETTE.shape == (NUM_CLASSES + 1, 3)


def class_id(name: str) -> int:
    """NYU40 id of a class name (case-insensitive)."""
    try:
        return CLASS_NAMES.index(name.lower())
    except ValueError:
        raise KeyError(f"unknown NYU40 class name {name!r}") from None


def class_color(nyu40_id: int) -> tuple[int, int, int]:
    """RGB colour of a NYU40 id (0..40)."""
    if not 0 <= nyu40_id <= NUM_CLASSES:
        raise KeyError(f"NYU40 id {nyu40_id} is outside 0..{NUM_CLASSES}")
    r, g, b = (int(v) for v in PALETTE[nyu40_id])
    return r, g, b


def check_label_map(labels: np.ndarray, what: str = "labels") -> np.ndarray:
    """Return ``labels`` as an array after checking it is a 2-D map of NYU40 ids (0..40)."""
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"{what}: expected a 2-D (H, W) label map, got shape {labels.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{what}: expected integer NYU40 ids, got dtype {labels.dtype}")
    if labels.size and (labels.min() < 0 or labels.max() > NUM_CLASSES):
        bad = np.unique(labels[(labels < 0) | (labels > NUM_CLASSES)])
        raise ValueError(f"{what}: ids {bad[:10].tolist()} are outside NYU40 0..{NUM_CLASSES}")
    return labels
