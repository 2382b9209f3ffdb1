"""The materials of a manifold by name: their index, one-hot weights, and weights written as text.

Weights of a combination of the training materials (``sum_i w_i table_i``, paper Eq. 4) are
given by users as ``"name:w, name:w"``; :func:`parse_weights` reads them against the
manifold's names, with a suggestion for a mistyped name (:func:`index`).
"""

import numpy as np

from .._util.checks import weight_sum
from ..errors import InputError, did_you_mean


def index(names, name):
    """Position of material ``name`` in ``names``; :class:`InputError` with the closest names otherwise."""
    try:
        return names.index(name)
    except ValueError:
        n = len(names)
        raise InputError(
            f"unknown material {name!r}{did_you_mean(name, names)}: this manifold has {n} materials "
            f"({', '.join(names[:6])}{', ...' if n > 6 else ''})"
        ) from None


def one_hot(names, name):
    """Weights selecting the training material ``name`` alone."""
    w = np.zeros(len(names))
    w[index(names, name)] = 1.0
    return w


def parse_weights(text, names):
    """Weights from ``"name:w, name:w"`` (unnamed materials get 0), ``(N,)`` float64.

    Raises
    ------
    InputError
        Unknown names, malformed entries, non-finite values or weights summing to 0.
    """
    w = np.zeros(len(names))
    entries = [e.strip() for e in str(text).split(",") if e.strip()]
    if not entries:
        raise InputError(f"weights {text!r}: expected 'name:weight, name:weight'")
    for e in entries:
        name, sep, value = e.rpartition(":")
        try:
            v = float(value)
        except ValueError:
            v = None
        if not sep or v is None or not np.isfinite(v) or ":" in name:
            raise InputError(
                f"weights {text!r}: entry {e!r} is not 'name:number' (commas separate entries)"
            )
        w[index(names, name.strip())] += v
    try:
        weight_sum(w)
    except InputError as e:
        raise InputError(f"weights {text!r}: {e}") from None
    return w
