"""The package's public names, and ``csa seg`` options that load without torch."""

from __future__ import annotations

import subprocess
import sys

import csa_core.seg as seg


def test_every_public_name_resolves():
    for name in seg.__all__:
        assert getattr(seg, name) is not None, name
    assert callable(seg.pretrain) and callable(seg.train_segmentation)


def test_registering_the_seg_commands_does_not_import_torch():
    code = (
        "import argparse, sys; from csa_core.cli import seg; "
        "seg.register(argparse.ArgumentParser().add_subparsers()); print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
