"""The direct renders of the main job's error-against-time plot are timed without compiling: with a
renderer that compiles once per sample count, more samples never take less time. The clock is
the test's own (each render advances it by the time it would take), so the test is exact on any
machine, however busy."""

from types import SimpleNamespace

import numpy as np

from mitsuba_manifold.apps import gi_comparison
from mitsuba_manifold.apps.gi_comparison import timed_render

COMPILE_S = 0.15


def test_direct_render_times_exclude_compiling_and_grow_with_spp(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(gi_comparison, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    compiled = set()

    def render(spp, seed):
        if spp not in compiled:  # the first render of a sample count compiles its kernels
            compiled.add(spp)
            clock[0] += COMPILE_S
        clock[0] += 0.002 * spp
        return spp

    times = [timed_render(render, spp, seed=1)[1] for spp in (1, 4, 16, 64)]
    # the compiling of each sample count (0.15 s) is in none of them
    np.testing.assert_allclose(times, [0.002 * spp for spp in (1, 4, 16, 64)], rtol=1e-9)
