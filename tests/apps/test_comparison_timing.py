"""The direct renders of the main job's error-against-time plot are timed without compiling: with a
renderer that compiles once per sample count, more samples never take less time."""

import time

from mitsuba_manifold.apps.gi_comparison import timed_render


def test_direct_render_times_exclude_compiling_and_grow_with_spp():
    compiled = set()

    def render(spp, seed):
        if spp not in compiled:  # the first render of a sample count compiles its kernels
            compiled.add(spp)
            time.sleep(0.15)
        time.sleep(0.002 * spp)
        return spp

    times = [timed_render(render, spp, seed=1)[1] for spp in (1, 4, 16, 64)]
    assert times == sorted(times), times
    assert times[0] < 0.1
