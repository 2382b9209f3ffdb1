"""weights32: float32 weights without subnormal values."""

import numpy as np

from mitsuba_manifold._util.float32 import TINY, weights32


def test_weights32_zeroes_only_the_subnormal_values_and_copies():
    w = np.array([0.5, 1e-39, -1e-40, 2e-38, -0.25, 1e-300, 0.0, TINY])
    out = weights32(w)
    assert out.dtype == np.float32
    assert np.array_equal(out, np.array([0.5, 0, 0, 2e-38, -0.25, 0, 0, TINY], np.float32))
    same = np.array([1e-39, 1.0], np.float32)
    assert weights32(same)[0] == 0 and same[0] != 0  # the input is left as it was
