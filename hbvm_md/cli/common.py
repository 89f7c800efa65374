"""What every ``hbvm-md`` subcommand shares: the parser class, the argument types, the default
output folder, printing, and the usage error that ``main`` turns into exit status 2.

Imported by :mod:`hbvm_md.cli.commands` and :mod:`hbvm_md.cli.ensemble`; it imports neither.
"""
from __future__ import annotations

import argparse

import numpy as np

DEFAULT_OUT = "hbvm-md-output"


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage block) and exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def _int_at_least(minimum: int):
    """An argparse type: an integer >= ``minimum`` (checked before any command runs)."""
    what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return v
    return parse


_positive_int = _int_at_least(1)


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def _say(*a):
    print(*a, flush=True)


# a command's own check of its arguments failed: main prints the message, exit status 2
class _UsageError(Exception):
    pass


def _fail(message: str):
    raise _UsageError(message)
