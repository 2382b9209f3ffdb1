"""Renders cut into short passes, so that Ctrl-C stops them promptly and cleanly.

A Dr.Jit kernel does not return to Python until it is done, and Mitsuba's ``render`` swallows
Ctrl-C; :func:`render_in_passes` cuts a render into passes of at most
:data:`SAMPLES_PER_PASS` paths (:func:`sample_passes`) and checks a
:class:`~mitsuba_manifold._util.interrupts.StopRequest` (the package's handling of Ctrl-C,
:mod:`mitsuba_manifold._util.interrupts`) after each: ``KeyboardInterrupt`` there, only
complete, listed files remain.
"""

from ..._util.interrupts import StopRequest

__all__ = ["SAMPLES_PER_PASS", "StopRequest", "render_in_passes", "sample_passes"]

#: Paths per render pass (a pass is the unit a stop request waits for).
SAMPLES_PER_PASS = 1 << 20


def sample_passes(spp, pixels, samples_per_pass=SAMPLES_PER_PASS):
    """Samples per pixel of each pass: ``spp`` split so that a pass traces at most
    ``samples_per_pass`` paths (at least 1 spp per pass); they sum to ``spp``.
    """
    per = max(1, min(int(spp), int(samples_per_pass) // max(1, int(pixels))))
    full, rest = divmod(int(spp), per)
    return [per] * full + ([rest] if rest else [])


def render_in_passes(scene, integrator, spp, seed=0, stop=None, sensor=0):
    """``mi.render`` cut into passes (:func:`sample_passes`), checking ``stop`` after each.

    One pass (the usual case for small images) is exactly ``mi.render(..., spp, seed)``; passes
    after the first use seeds ``(seed + k * 0x9E3779B9) mod 2^32``, and the image is their
    sample-weighted mean (linear RGB of the film's crop window, float32, whatever its pixel
    format).

    Parameters
    ----------
    stop : StopRequest, optional
        Default: a new one, active during the render (Ctrl-C then raises
        ``KeyboardInterrupt`` at the end of the current pass).
    """
    import mitsuba as mi
    import numpy as np

    from ..integrators.common import developed_rgb

    if stop is None:
        with StopRequest() as own:
            return render_in_passes(scene, integrator, spp, seed, own, sensor)
    w, h = (int(v) for v in scene.sensors()[sensor].film().crop_size())
    total = None
    for k, n in enumerate(sample_passes(spp, w * h)):
        stop.rearm()
        mi.render(
            scene,
            integrator=integrator,
            spp=n,
            seed=(seed + k * 0x9E3779B9) & 0xFFFFFFFF,
            sensor=sensor,
        )
        img = developed_rgb(scene.sensors()[sensor].film()).astype(
            np.float64
        )  # RGB, any pixel format
        total = img * n if total is None else total + img * n
        if integrator.should_stop():  # Mitsuba's own SIGINT handler ran during the pass
            stop.requested = True
        stop.check()
    return (total / int(spp)).astype(np.float32)
