"""What every command line shares (stg-render, stg-view, and stg_train's through stg_train.cli.common):
the parser that answers a bad argument in one line, the argument types, the error line.

Every problem with the input ends a command with one line on stderr, `PROG: error: <option or file>:
<problem>`, and exit code 2: no usage block, no traceback. This module imports only the standard
library, so `--help` and argument errors answer before numpy, numba or torch are loaded.
"""
from __future__ import annotations

import argparse
import math
import sys

#: The largest image side a command accepts (pixels): larger is a typo, not a picture.
MAX_SIDE = 16384


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line, `PROG: error: ...`, and exit code 2 (argparse's own
    print the usage block first). Subparsers are of the same class."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def error(prog: str, message: str) -> int:
    """Print `prog: error: message` on stderr, on one line (a message of several lines is joined); returns
    2, the exit code of bad input."""
    message = " ".join(line.strip() for line in str(message).splitlines() if line.strip())
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


def given_options(parser: argparse.ArgumentParser, argv) -> set[str]:
    """The `dest` names of the options that `argv` sets (not left at their defaults)."""
    import copy

    probe = copy.deepcopy(parser)
    for action in probe._actions:
        action.default = argparse.SUPPRESS
        action.required = False
    for group in probe._mutually_exclusive_groups:
        group.required = False
    return set(vars(probe.parse_known_args(argv)[0]))


def _int_at_least(text: str, minimum: int, wanted: str) -> int:
    """int(text), or argparse.ArgumentTypeError "must be <wanted>, got ..." when it is not one or is
    below `minimum`."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < minimum:
        raise argparse.ArgumentTypeError(f"must be {wanted}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    return _int_at_least(text, 1, "a positive integer")


def nonnegative_int(text: str) -> int:
    return _int_at_least(text, 0, "an integer 0 or more")


def finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


def image_size(text: str, minimum: int = 1) -> tuple[int, int]:
    """WIDTHxHEIGHT -> (width, height), each side in [minimum, MAX_SIDE]."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 640x360, got {text!r}") from None
    if not (minimum <= w <= MAX_SIDE and minimum <= h <= MAX_SIDE):
        raise argparse.ArgumentTypeError(f"each side must be {minimum}..{MAX_SIDE} pixels, got {text!r}")
    return w, h


def port(text: str) -> int:
    """A TCP port 0..65535 (0: any free port)."""
    if not text.isdigit() or int(text) > 65535:
        raise argparse.ArgumentTypeError(f"a port is a number 0..65535, got {text!r}")
    return int(text)
