"""Device choice for every torch component: CUDA when available, overridable by name.

The same code runs on CPU and CUDA; callers pass ``None``/``"auto"`` or a device name.
"""

from __future__ import annotations

import torch

from csa_core.errors import CSAInputError


def resolve_device(name: str | torch.device | None = None) -> torch.device:
    """``None`` or ``"auto"``: ``cuda`` if available, else ``cpu``; otherwise the named device,
    checked."""
    if isinstance(name, torch.device):
        return name
    if name is None or name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise CSAInputError("--device", f"not a torch device: {name!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CSAInputError(
            "--device", "CUDA was requested but this machine has no usable CUDA GPU"
        )
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise CSAInputError(
            "--device", f"{name}: this machine has {torch.cuda.device_count()} CUDA device(s)"
        )
    return dev
