"""Device choice (csa_core/device.py): names are checked before any tensor is made."""

import pytest
import torch

from csa_core.device import resolve_device
from csa_core.errors import CSAInputError


def test_auto_and_cpu_resolve_without_a_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device(None) == resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(CSAInputError, match="--device: CUDA was requested"):
        resolve_device("cuda")


def test_a_cuda_index_the_machine_lacks_is_refused_by_name(monkeypatch):
    """``cuda:3`` on a one-GPU machine fails here, naming --device, not at the first allocation."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(CSAInputError, match=r"--device: cuda:3: this machine has 1 CUDA device"):
        resolve_device("cuda:3")


def test_a_name_torch_does_not_know_is_refused():
    with pytest.raises(CSAInputError, match="--device: not a torch device: 'gpu0'"):
        resolve_device("gpu0")
