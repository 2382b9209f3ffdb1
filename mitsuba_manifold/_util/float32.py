"""Weights as float32 operands of the products that combine tables.

A float64 weight far below float32's range (a Gaussian taper far from a material) becomes a
subnormal float32, and x86 cores take a slow microcode path for every multiply with a
subnormal operand: a matrix product with a few of them in its weights runs many times slower
than with zeros there. Such a weight contributes less than ``2^-126 |table|``: nothing at
float32 precision next to the other weights of a combination summing to 1.
"""

from __future__ import annotations

import numpy as np

#: The smallest normal float32.
TINY = np.finfo(np.float32).tiny


def weights32(w) -> np.ndarray:
    """``w`` as a new float32 array with its subnormal values (``|w| < TINY``) set to 0."""
    out = np.array(w, dtype=np.float32)
    out[np.abs(out) < TINY] = 0.0
    return out
