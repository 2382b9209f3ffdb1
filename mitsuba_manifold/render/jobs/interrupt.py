"""Ctrl-C that stops long renders promptly and cleanly.

A Dr.Jit kernel does not return to Python until it is done, and while Mitsuba's C++
``render`` runs, its own SIGINT handler replaces Python's: it only asks the integrator to
wind down (``cancel()``, which a JIT render ignores) and swallows the signal, so a loop
over renders went on. :class:`StopRequest` turns SIGINT into a flag instead (callers also
set it when ``integrator.should_stop()`` reports Mitsuba's cancel); renders are cut into short passes
(:func:`sample_passes`) and call :meth:`StopRequest.check` between passes and between
images, which raises ``KeyboardInterrupt`` there: only complete, listed files remain.
A second Ctrl-C while waiting for the pass to end stops at once (the default handler).
"""

from __future__ import annotations

import signal
import threading
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    pass
    import numpy as np


#: Paths per render pass (a pass is the unit a stop request waits for).
SAMPLES_PER_PASS = 1 << 20


class StopRequest:
    """Context manager: while active, the first SIGINT sets :attr:`requested`.

    Outside the main thread (where signals cannot be handled) it does nothing.
    """

    def __init__(self) -> None:
        self.requested = False
        self._previous = None
        self._active = False

    def _handle(self, signum, frame) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)  # a second Ctrl-C: at once

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._active = True
        return self

    def __exit__(self, *exc) -> Literal[False]:
        if self._active:
            previous = self._previous
            signal.signal(
                signal.SIGINT, signal.default_int_handler if previous is None else previous
            )
            self._previous, self._active = None, False
        return False

    def rearm(self) -> None:
        """Install the flag's handler again (while active, before the first Ctrl-C).

        Mitsuba's ``render`` installs its own SIGINT handler, which passes the signal on to the
        handler it found installed; whatever a render left installed, the next pass then passes
        Ctrl-C on to this one.
        """
        main = threading.current_thread() is threading.main_thread()  # signals: there only
        if self._active and main and not self.requested:
            signal.signal(signal.SIGINT, self._handle)

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed; else :meth:`rearm` for what follows
        (every loop of renders checks between its passes).
        """
        if self.requested:
            raise KeyboardInterrupt("stopped by Ctrl-C")
        self.rearm()


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
