"""BLAS on one thread for the whole process (:func:`one_thread`, the package's one way to ask
for it), and in-place sums of float32 images, ``y += a * x``, by BLAS ``saxpy`` on one thread.

BLAS limits are process-wide: two threads that each set and restore them in their own context
would restore what the other set. :func:`one_thread` counts its users in every thread; the last
one out restores the limits the first one in found.

The sums: one pass over ``x`` and ``y`` (NumPy needs a product into a temporary, then a sum: twice the
memory traffic). BLAS would split a long ``saxpy`` over its threads, which for an image costs
more than it gains: the threads wait on each other (far longer on a machine whose other cores
are busy) and then spin on cores other work needs. A run of sums goes inside
:func:`one_thread`, which holds BLAS to one thread (``threadpoolctl``) while any thread of the
process is inside it.
"""

from __future__ import annotations

import contextlib
import threading
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Iterator


_lock = threading.Lock()
_state = {"inside": 0, "limit": None, "controller": None}


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """BLAS on one thread while any thread is inside (nested and concurrent uses are counted;
    the last one out restores the limits found by the first one in).
    """
    with _lock:
        if not _state["inside"]:
            if _state["controller"] is None:
                from threadpoolctl import ThreadpoolController

                _state["controller"] = ThreadpoolController()
            _state["limit"] = _state["controller"].limit(limits=1, user_api="blas")
            release_control()
        _state["inside"] += 1
    try:
        yield
    finally:
        with _lock:
            _state["inside"] -= 1
            if not _state["inside"]:
                _state["limit"].restore_original_limits()
                _state["limit"] = None
                release_control()


def release_control() -> None:
    """Let the next thread set OpenBLAS's limits: threadpoolctl lets one Python thread at a time
    change them (the one that last did, until it lets go; the others' changes do nothing).
    """
    try:
        from threadpoolctl import OpenBLASController
    except ImportError:  # pragma: no cover - depends on the threadpoolctl version
        return
    clear = getattr(OpenBLASController, "clear_controlling_thread", None)
    if clear is not None:
        clear()


def axpy(y, x, a) -> np.ndarray:
    """``y += a * x`` in place; ``y`` and ``x`` float32 C-contiguous arrays of one shape (run
    inside :func:`one_thread`).

    Raises ``ValueError`` for any other ``y`` or ``x`` (a copy would be summed, not ``y``).
    """
    if not (
        y.dtype == x.dtype == np.float32
        and y.shape == x.shape
        and y.flags.c_contiguous
        and x.flags.c_contiguous
        and y.flags.writeable
    ):
        raise ValueError(
            f"axpy needs two C-contiguous float32 arrays of one shape, y writable; got "
            f"{y.dtype} {y.shape} and {x.dtype} {x.shape}"
        )
    from scipy.linalg.blas import saxpy  # here, not at import: tools that never sum skip SciPy

    flat = y.reshape(-1)
    out = saxpy(x.reshape(-1), flat, a=float(a))
    if out is not flat and not np.shares_memory(out, flat):  # not in place: keep the sum
        flat[...] = out
    return y
