"""Mapping raw ScanNet label ids (``label-filt``) to NYU40 with
``scannetv2-labels.combined.tsv``."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from csa_core.errors import CSAInputError


def load_raw_to_nyu40(tsv: str | Path) -> np.ndarray:
    """Lookup table ``lut[raw_id] -> nyu40 id`` (uint8, 0 for ids the file does not list).

    Needs the columns ``id`` and ``nyu40id`` of ScanNet's tab-separated label table.
    """
    tsv = Path(tsv)
    if not tsv.is_file():
        raise CSAInputError(tsv, "label map file not found")
    pairs: list[tuple[int, int]] = []
    with tsv.open(newline="") as fh:
        reader = csv.DictReader(fh, delimiter="\t")
        missing = {"id", "nyu40id"} - set(reader.fieldnames or [])
        if missing:
            raise CSAInputError(
                tsv, f"missing column(s) {', '.join(sorted(missing))} (need 'id' and 'nyu40id')"
            )
        for line_no, row in enumerate(reader, start=2):
            try:
                raw, nyu = int(row["id"]), int(row["nyu40id"] or 0)
            except (TypeError, ValueError):
                raise CSAInputError(
                    tsv, f"line {line_no}: 'id' and 'nyu40id' must be integers"
                ) from None
            if not 0 <= nyu <= 40:
                raise CSAInputError(tsv, f"line {line_no}: nyu40id {nyu} out of range 0..40")
            if not 0 <= raw <= 65535:
                raise CSAInputError(tsv, f"line {line_no}: id {raw} out of range 0..65535")
            pairs.append((raw, nyu))
    lut = np.zeros(65536, dtype=np.uint8)
    for raw, nyu in pairs:
        lut[raw] = nyu
    return lut
