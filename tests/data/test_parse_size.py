"""The one image-size parser behind the CLI, the server's jobs and the synthesiser."""

from __future__ import annotations

import argparse

import pytest

from csa_core.cli.args import size_arg
from csa_core.data.camera import parse_size
from csa_core.errors import CSAInputError
from server.jobs.inputs import parse_size as job_size


def test_sizes_parse_to_width_height():
    assert parse_size("160x120") == (160, 120)
    assert parse_size("64X48") == (64, 48)
    assert size_arg("320x240") == (320, 240)
    assert job_size("80x60") == (80, 60) and job_size(None) is None


@pytest.mark.parametrize("bad", ["160", "160*120", "x120", "-5x10", "4x4", "9000x10", "ax b"])
def test_bad_sizes_name_the_field(bad):
    with pytest.raises(CSAInputError) as err:
        parse_size(bad, "size")
    assert err.value.where == "size"
    with pytest.raises(argparse.ArgumentTypeError, match="WIDTHxHEIGHT|within 8..8192"):
        size_arg(bad)
