"""Renders cut into short passes, so that Ctrl-C stops them promptly and cleanly.

A Dr.Jit kernel does not return to Python until it is done, and Mitsuba's ``render`` swallows
Ctrl-C; :func:`render_in_passes` cuts a render into passes of at most
:data:`SAMPLES_PER_PASS` paths (:func:`sample_passes`) and checks a
:class:`~mitsuba_manifold._util.interrupts.StopRequest` (the package's handling of Ctrl-C,
:mod:`mitsuba_manifold._util.interrupts`) after each: ``KeyboardInterrupt`` there, only
complete, listed files remain.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..._util.interrupts import StopRequest

if TYPE_CHECKING:
    import numpy as np


__all__ = ["SAMPLES_PER_PASS", "StopRequest", "render_in_passes", "sample_passes"]

#: Paths per render pass (a pass is the unit a stop request waits for).
SAMPLES_PER_PASS = 1 << 20


def sample_passes(spp, pixels, samples_per_pass=SAMPLES_PER_PASS) -> list[int]:
    """Samples per pixel of each pass: ``spp`` split so that a pass traces at most
    ``samples_per_pass`` paths (at least 1 spp per pass); they sum to ``spp``.
    """
    per = max(1, min(int(spp), int(samples_per_pass) // max(1, int(pixels))))
    full, rest = divmod(int(spp), per)
    return [per] * full + ([rest] if rest else [])


#: Seed step between passes: pass ``k`` is seeded ``(seed + k * SEED_STEP) mod 2^32``.
SEED_STEP = 0x9E3779B9


def render_in_passes(scene, integrator, spp, seed=0, stop=None, sensor=0) -> np.ndarray:
    """``mi.render`` cut into passes (:func:`sample_passes`), checking ``stop`` after each.

    One pass (the usual case for small images) is exactly ``mi.render(..., spp, seed)``; passes
    after the first use seeds ``(seed + k * 0x9E3779B9) mod 2^32``, and the image is their
    sample-weighted mean (linear RGB of the film's crop window, float32, whatever its pixel
    format): :func:`render_passes`'s image.

    Parameters
    ----------
    stop : StopRequest, optional
        Default: a new one, active during the render (Ctrl-C then raises
        ``KeyboardInterrupt`` at the end of the current pass).
    """
    return render_passes(scene, integrator, spp, seed, stop, sensor)[0]


def render_passes(
    scene,
    integrator,
    spp,
    seed=0,
    stop=None,
    sensor=0,
    samples_per_pass=SAMPLES_PER_PASS,
    min_passes=1,
    progress=None,
) -> tuple:
    """``mi.render`` cut into passes, as :func:`render_in_passes`, with what the passes say of
    their own noise.

    Parameters
    ----------
    samples_per_pass : int
        Paths per pass at most (:func:`sample_passes`).
    min_passes : int
        Passes at least, where ``spp`` allows (two measure the render's noise).
    progress : callable, optional
        ``progress(done, spp)`` after each pass.

    Returns
    -------
    image : ndarray float32 (H, W, 3)
        The sample-weighted mean of the passes.
    pixel_se : ndarray float32 (H, W, 3)
        Its standard error per value (:func:`~mitsuba_manifold.imaging.metrics.pass_standard_error`;
        NaN for one pass).
    passes : int
    """
    import mitsuba as mi
    import numpy as np

    from ...imaging.metrics import pass_standard_error
    from ..integrators.common import developed_rgb

    if stop is None:
        with StopRequest() as own:
            return render_passes(
                scene, integrator, spp, seed, own, sensor, samples_per_pass, min_passes, progress
            )
    spp = int(spp)
    w, h = (int(v) for v in scene.sensors()[sensor].film().crop_size())
    per_pass = min(int(samples_per_pass), max(1, spp // max(1, int(min_passes))) * w * h)
    passes = sample_passes(spp, w * h, per_pass)
    acc, acc2, done = 0.0, 0.0, 0
    for k, n in enumerate(passes):
        stop.rearm()
        mi.render(
            scene,
            integrator=integrator,
            spp=n,
            seed=(seed + k * SEED_STEP) & 0xFFFFFFFF,
            sensor=sensor,
        )
        img = developed_rgb(scene.sensors()[sensor].film()).astype(
            np.float64
        )  # RGB, any pixel format
        acc, acc2, done = acc + img * n, acc2 + img * img * n, done + n
        if integrator.should_stop():  # Mitsuba's own SIGINT handler ran during the pass
            stop.requested = True
        stop.check()
        if progress is not None:
            progress(done, spp)
    se = pass_standard_error(acc, acc2, done, len(passes))
    return (acc / spp).astype(np.float32), se.astype(np.float32), len(passes)
