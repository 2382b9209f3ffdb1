"""What a value from a request may be: numbers as JSON writes them, shown briefly in messages."""

import re

import numpy as np

#: What a number may look like (as JSON writes them, plus nan/inf to name them in the error);
#: Python's float() would also take "1_0", " 1 ", "١٢" and 4000-digit integers.
NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?|[+-]?(?:nan|inf|infinity)",
                     re.IGNORECASE)


def show(value, limit=60):
    """``repr`` of a value from a request, cut to ``limit`` characters (messages stay one line)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 5] + " ...>"


def to_float(value):
    """A number from a request as a float: ints, floats and number text only (no bools, no
    "1_0"); an integer too large for a float gives +-1e308 (refused as out of range)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, str, np.integer, np.floating)):
        raise TypeError(f"not a number: {show(value)}")
    if isinstance(value, str) and not NUMBER.fullmatch(value):
        raise ValueError(f"not a number: {show(value)}")
    try:
        return float(value)
    except OverflowError:
        return 1e308 if value > 0 else -1e308
