"""Argument helpers shared by the command-line tools (parsing and progress only; the work is in the library)."""

import argparse
import sys

from ..errors import MitsubaManifoldError

#: What a tool reports as a one-line error (anything else is a bug and keeps its traceback).
ERRORS = (MitsubaManifoldError, OSError)


def parse_list(text):
    """'a,b,c' -> ['a', 'b', 'c']."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list, got {text!r}")
    return items


def parse_resolution(text):
    """'90,90,180' -> (90, 90, 180)."""
    try:
        dims = tuple(int(v) for v in text.split(","))
    except ValueError:
        dims = ()
    if len(dims) != 3 or min(dims) < 1:
        raise argparse.ArgumentTypeError(f"resolution must be three positive integers like 90,90,180, got {text!r}")
    return dims


def parse_floats(text):
    """'0.3, -1.2' or '0.3 -1.2' -> [0.3, -1.2]."""
    try:
        return [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers like '0.3,-1.2', got {text!r}") from None


def fail(error, code=2):
    """Print an error for the user and exit."""
    print(f"error: {error}", file=sys.stderr)
    sys.exit(code)
