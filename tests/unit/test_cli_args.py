"""The CLI's argument types: positive_float and nonnegative_float share one
parse (cli.args._seconds); their verdicts and messages, value by value."""

from __future__ import annotations

import argparse

import pytest

from zplatform.cli.args import nonnegative_float, positive_float


@pytest.mark.parametrize(
    ("text", "positive", "nonnegative"),
    [
        ("1.5", 1.5, 1.5),
        (" 2 ", 2.0, 2.0),
        ("1e-9", 1e-9, 1e-9),
        ("0", "must be > 0, got 0", 0.0),
        ("-0", "must be > 0, got -0", -0.0),
        ("-1", "must be > 0, got -1", "must be >= 0, got -1"),
        ("nan", "must be > 0, got nan", "must be >= 0, got nan"),
        ("inf", "must be > 0, got inf", "must be >= 0, got inf"),
        ("-inf", "must be > 0, got -inf", "must be >= 0, got -inf"),
        (
            "abc",
            "expected a number of seconds, got 'abc'",
            "expected a number of seconds, got 'abc'",
        ),
        ("", "expected a number of seconds, got ''", "expected a number of seconds, got ''"),
    ],
)
def test_seconds_verdicts(text: str, positive: float | str, nonnegative: float | str) -> None:
    for parse, want in ((positive_float, positive), (nonnegative_float, nonnegative)):
        if isinstance(want, str):
            with pytest.raises(argparse.ArgumentTypeError) as ei:
                parse(text)
            assert str(ei.value) == want
        else:
            assert parse(text) == want
