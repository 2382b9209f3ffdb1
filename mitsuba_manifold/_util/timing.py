"""Wall-clock timing of repeated calls (medians; the benchmarks and the main job report them)."""

from __future__ import annotations

import time

import numpy as np


def median_time(fn, repeats) -> tuple[float, list[float]]:
    """Median wall time (s) of ``repeats`` calls of ``fn()``, and every time measured."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), times
