"""Worker processes owned by the process that starts them: they end when it ends, however it ends.

:func:`owned_pool` starts a :class:`multiprocessing.pool.Pool` of *spawned* processes (fresh
interpreters: they inherit no descriptor, so a folder lock of the parent, :mod:`.locking`,
is never held by a worker) whose initializer asks Linux to SIGKILL each one when its
parent dies (``prctl(PR_SET_PDEATHSIG)``, through ctypes) and leaves Ctrl-C to the parent.
When the block ends by an exception (Ctrl-C included) the workers are terminated at once;
when the parent is killed (SIGKILL, SIGTERM) the kernel ends them. Elsewhere than Linux
the death signal is not available and the parent's normal exits still end them.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterator
    from typing import Any


from . import interrupts

#: ``PR_SET_PDEATHSIG`` of ``<linux/prctl.h>``.
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid) -> None:
    """In a worker: ignore SIGINT (the parent handles Ctrl-C), and be killed when the parent dies."""
    interrupts.ignore()
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before the death signal was asked for
        os._exit(1)


@contextlib.contextmanager
def owned_pool(processes) -> Iterator[Any]:
    """A pool of ``processes`` spawned workers that end with this process (see the module notes)."""
    pool = multiprocessing.get_context("spawn").Pool(
        processes, initializer=die_with_parent, initargs=(os.getpid(),)
    )
    try:
        yield pool
    except BaseException:
        pool.terminate()
        pool.join()
        raise
    pool.close()
    pool.join()
