"""The argparse types and one-line error text shared by the CLI and the benchmark (SDFCARLib/cli_types.py)."""

from __future__ import annotations

import argparse
import math

import pytest

from SDFCARLib.cli_types import one_line, positive_float, positive_int


def test_positive_int_and_float_accept_and_refuse_with_the_reason():
    assert positive_int("3") == 3 and positive_float("0.25") == 0.25
    for bad in ("0", "-2", "x", "1.5"):
        with pytest.raises(argparse.ArgumentTypeError, match="must be a positive integer"):
            positive_int(bad)
    for bad in ("0", "-1e-3", "nan", "inf", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="must be a positive number"):
            positive_float(bad)
    assert math.isfinite(positive_float("1e-9"))


def test_one_line_joins_the_message_and_names_the_type_on_request():
    error = RuntimeError("first line\n   second\tline ")
    assert one_line(error) == "first line second line"
    assert one_line(error, with_type=True) == "RuntimeError: first line second line"
    assert one_line(ValueError()) == one_line(ValueError("  "), with_type=True) == "ValueError"
