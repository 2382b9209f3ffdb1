"""The process's peak memory, as the main job reports it per stage."""

import sys

try:
    import resource
except ImportError:  # not on Windows
    resource = None


def peak_rss():
    """The largest resident set size this process has had so far, in bytes (``getrusage``'s
    ``ru_maxrss``: Linux's ``VmHWM``, what ``/usr/bin/time -v`` reports), or None where the
    system does not say.
    """
    if resource is None:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak) if sys.platform == "darwin" else int(peak) * 1024  # macOS: bytes; else kB
