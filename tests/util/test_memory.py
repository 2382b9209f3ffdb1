"""Large arrays mapped at once (NumPy only)."""

import numpy as np

from mitsuba_manifold._util.memory import prefaulted


def test_prefaulted_array_is_an_ordinary_writable_array():
    a = prefaulted((3, 1000), np.float32)
    assert a.shape == (3, 1000) and a.dtype == np.float32
    assert a.flags.c_contiguous and a.flags.writeable
    a[...] = np.arange(3000, dtype=np.float32).reshape(3, 1000)
    assert a[2, 999] == 2999 and a.sum(dtype=np.float64) == 2999 * 3000 / 2
    assert prefaulted((0, 5)).shape == (0, 5)
