"""What a value from a request may be: numbers as JSON writes them, shown briefly in messages;
the explorer's request validation (latent points, numbers, map extents and coordinates, path kinds).
"""

import re

import numpy as np

from ...._util import checks as validate
from ....errors import InputError
from ....manifold import paths as path_kinds

#: What a number may look like (as JSON writes them, plus nan/inf to name them in the error);
#: Python's float() would also take "1_0", " 1 ", "١٢" and 4000-digit integers.
NUMBER = re.compile(
    r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?|[+-]?(?:nan|inf|infinity)",
    re.IGNORECASE,
)


def show(value, limit=60):
    """``repr`` of a value from a request, cut to ``limit`` characters (messages stay one line)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 5] + " ...>"


def to_float(value):
    """A number from a request as a float: ints, floats and number text only (no bools, no
    "1_0"); an integer too large for a float gives +-1e308 (refused as out of range).
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(
        value, (int, float, str, np.integer, np.floating)
    ):
        raise TypeError(f"not a number: {show(value)}")
    if isinstance(value, str) and not NUMBER.fullmatch(value):
        raise ValueError(f"not a number: {show(value)}")
    try:
        return float(value)
    except OverflowError:
        return 1e308 if value > 0 else -1e308


def latent_point(manifold, value, what="x"):
    """Latent point of ``manifold`` from a list of numbers or ``"a,b"`` text; a training
    material's name gives its latent point.
    """
    q = manifold.q
    if isinstance(value, str) and value.strip() in manifold.names:
        return manifold.latent[manifold.index(value.strip())].copy()
    if isinstance(value, str):
        parts = [p for p in value.replace(",", " ").split() if p]
    elif isinstance(value, (list, tuple)):
        parts = list(value)
    else:
        raise InputError(
            f"{what} must be {q} numbers like '0.1,-0.4' or a material name, got {show(value)}"
        )
    if len(parts) != q:
        if isinstance(value, str) and len(parts) == 1 and not NUMBER.fullmatch(parts[0]):
            raise InputError(
                f"{what}: unknown material {show(value)} (not one of the manifold's "
                f"{manifold.n} materials) and not numbers"
            )
        raise InputError(
            f"{what} has {len(parts)} number(s); the manifold is {q}-dimensional: give {q}"
        )
    try:
        arr = np.array([to_float(v) for v in parts], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            f"{what} must be {q} numbers (like 0.25 or -1.5e-2), got {show(value)}"
        ) from None
    if not np.isfinite(arr).all():
        raise InputError(f"{what} contains NaN or Inf: {show(value)}")
    if np.abs(arr).max() > 1e6:
        raise InputError(
            f"{what} = {show(value)} is absurdly far from the latent points (|x| > 1e6)"
        )
    return arr


def number(value, what, lo, hi, default):
    """A number of a request in ``[lo, hi]``; ``default`` when absent or empty."""
    if value is None or value == "":
        return default
    try:
        v = to_float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number, got {show(value)}") from None
    try:
        return validate.finite(what, v, lo, hi)
    except InputError:
        raise InputError(
            f"{what} must be a finite number in [{lo:g}, {hi:g}], got {show(value)}"
        ) from None


def extent(text):
    """The extent ``(x_min, x_max, y_min, y_max)`` of a latent map from a request."""
    try:
        b = [
            to_float(v)
            for v in (str(text).replace(",", " ").split() if isinstance(text, str) else text)
        ]
    except (TypeError, ValueError):
        b = []
    if (
        len(b) != 4
        or not np.isfinite(b).all()
        or max(map(abs, b)) > 1e6
        or not b[0] < b[1]
        or not b[2] < b[3]
        or min(b[1] - b[0], b[3] - b[2]) < 1e-6
    ):
        raise InputError(
            f"extent must be 'x_min,x_max,y_min,y_max' (finite, min < max, span >= 1e-6), "
            f"got {show(text)}"
        )
    return tuple(b)


def map_dims(manifold, dims):
    """The two latent coordinates of a map of ``manifold`` from a request."""
    q = manifold.q
    if isinstance(dims, str):
        dims = [d for d in dims.replace(",", " ").split() if d]
    ok = isinstance(dims, (list, tuple)) and all(
        (isinstance(d, str) and d.isascii() and d.isdigit() and len(d) < 4)
        or (isinstance(d, int) and not isinstance(d, bool))
        for d in dims
    )
    if not ok:
        raise InputError(f"dims must be two latent coordinates like '0,1', got {show(dims)}")
    dims = tuple(int(d) for d in dims)
    if len(dims) != 2 or dims[0] == dims[1] or not all(0 <= d < q for d in dims):
        raise InputError(
            f"dims must be two different coordinates in 0..{q - 1}, got {show(list(dims))}"
        )
    return dims


def path_kind(kind):
    """A path kind of a request (one of :data:`~mitsuba_manifold.manifold.paths.KINDS`)."""
    if not isinstance(kind, str) or kind not in path_kinds.KINDS:
        raise InputError(f"kind must be one of {list(path_kinds.KINDS)}, got {show(kind)}")
    return kind
