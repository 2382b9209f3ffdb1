"""The process's peak memory, as the main job reports it per stage, and large arrays mapped at once."""

from __future__ import annotations

import mmap
import sys

import numpy as np

try:
    import resource
except ImportError:  # not on Windows
    resource = None


def peak_rss() -> int | None:
    """The largest resident set size this process has had so far, in bytes (``getrusage``'s
    ``ru_maxrss``: Linux's ``VmHWM``, what ``/usr/bin/time -v`` reports), or None where the
    system does not say.
    """
    if resource is None:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak) if sys.platform == "darwin" else int(peak) * 1024  # macOS: bytes; else kB


def prefaulted(shape, dtype=np.float32) -> np.ndarray:
    """A new uninitialised array of ``shape`` whose memory is mapped at once, for a large array
    that is about to be filled whole.

    On Linux an anonymous ``mmap`` with ``MAP_POPULATE``: the kernel maps every page in one
    call (no page fault per page as the array is first written, and no wait for huge pages to
    be assembled); the memory is returned when the array is freed. Elsewhere ``np.empty``.
    """
    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    flags = getattr(mmap, "MAP_POPULATE", None)
    if flags is None or size == 0:
        return np.empty(shape, dtype)
    buf = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | flags)
    return np.frombuffer(buf, dtype=dtype).reshape(shape)
