"""Ctrl-C (SIGINT) for the whole package: the one module that installs a handler for it.

A process meets Ctrl-C in one of four situations, each with its call here:

- :func:`exit_while_starting`: a tool's script, before it has imported anything (Mitsuba,
  Dr.Jit and SciPy take most of a tool's first second): one ``error:`` line and exit status
  :data:`INTERRUPTED` at once, nothing written.
- :class:`Noted`: a tool's ``main`` running (:func:`mitsuba_manifold.apps.cli.common.guarded`):
  ``KeyboardInterrupt`` as Python's own handler raises it, and a note that it was Ctrl-C (an
  import the interrupt cut half-way can surface as another exception). A whole process that
  has finished ignores a late Ctrl-C.
- :class:`StopRequest`: a loop of renders: the first Ctrl-C only sets a flag, checked between
  passes and between images, which then raises ``KeyboardInterrupt``; a second one raises at
  once.
- :func:`ignore`: a worker process (its parent handles Ctrl-C).

Signals are handled in the main thread only; elsewhere each of these leaves the handler alone.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Literal

#: Exit status of a run stopped by Ctrl-C (128 + SIGINT), as shells report it.
INTERRUPTED = 130
#: What a tool's script says when Ctrl-C comes while it starts.
STARTING_MESSAGE = "error: interrupted while starting; nothing was written"


def _main_thread() -> bool:
    """True in the main thread, the only one where Python runs signal handlers."""
    return threading.current_thread() is threading.main_thread()


def exit_while_starting(message=STARTING_MESSAGE) -> None:
    """Until a later handler replaces it: Ctrl-C writes ``message`` (one line) to stderr and
    ends the process at once with :data:`INTERRUPTED`, no traceback.
    """

    def handle(signum, frame) -> None:
        sys.stderr.write(message + "\n")
        os._exit(INTERRUPTED)

    if _main_thread():
        signal.signal(signal.SIGINT, handle)


def ignore() -> None:
    """Ignore Ctrl-C from now on (a worker whose parent handles it; a finished process)."""
    if _main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class Noted:
    """Ctrl-C raises ``KeyboardInterrupt``, as Python's own handler does, and sets :attr:`seen`.

    :meth:`install` it, then :meth:`restore` the handler it replaced (or ignore Ctrl-C in a
    whole process that has finished: everything was written, and a late Ctrl-C must not turn
    into a traceback while the interpreter shuts down).
    """

    def __init__(self) -> None:
        self.seen = False
        self.previous = None

    def _handle(self, signum, frame) -> None:
        self.seen = True
        raise KeyboardInterrupt

    def install(self) -> Noted:
        if _main_thread():
            self.previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def restore(self, finished_process=False) -> None:
        if self.previous is None:
            return
        signal.signal(signal.SIGINT, signal.SIG_IGN if finished_process else self.previous)
        self.previous = None


class StopRequest:
    """Context manager: while active, the first Ctrl-C sets :attr:`requested`; a second one
    raises ``KeyboardInterrupt`` at once (Python's default handler).

    A Dr.Jit kernel does not return to Python until it is done, and while Mitsuba's C++
    ``render`` runs, its own SIGINT handler replaces Python's: it only asks the integrator to
    wind down (``cancel()``, which a JIT render ignores) and swallows the signal. So a loop of
    renders cuts them into short passes and calls :meth:`check` between passes and between
    images (callers also set :attr:`requested` when ``integrator.should_stop()`` reports
    Mitsuba's cancel): only complete, listed files remain. Leaving restores the handler found
    on entering. Outside the main thread it does nothing.
    """

    def __init__(self) -> None:
        self.requested = False
        self._previous = None
        self._active = False

    def _handle(self, signum, frame) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)  # a second Ctrl-C: at once

    def __enter__(self) -> StopRequest:
        if _main_thread():
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
        if self._active and _main_thread() and not self.requested:
            signal.signal(signal.SIGINT, self._handle)

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed; else :meth:`rearm` for what follows
        (every loop of renders checks between its passes).
        """
        if self.requested:
            raise KeyboardInterrupt("stopped by Ctrl-C")
        self.rearm()
