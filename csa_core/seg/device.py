"""Where segmentation networks run: CUDA when present, else CPU, unless the caller says."""

from __future__ import annotations

import torch

from csa_core.errors import CSAInputError


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """``None`` or ``"auto"`` picks ``cuda`` when available, else ``cpu``; anything else is checked."""
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise CSAInputError("--device", f"not a torch device: {device!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CSAInputError(
            "--device", "CUDA was requested but this machine has no usable CUDA GPU"
        )
    return dev
