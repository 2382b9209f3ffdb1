"""Run ``tools/explore.py`` in its own process (benchmarks, browser tests, screenshots).

:func:`start` runs ``python3 -m mitsuba_manifold.apps.cli.explore --port 0`` and returns once it
prints its URL; :func:`stop` stops it as Ctrl-C does. :func:`find_chromium` finds the
system Chromium that Playwright drives (it cannot download its own here).
"""

import os
import shutil
import time

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium():
    """Path of a system Chromium, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def start(bases, manifold=None, extra=(), timeout=300, refine=False):
    """Run the explore CLI in a subprocess on a free port; returns ``(process, url)``.

    Waits for the line with the URL (the bases are then in memory). ``refine``: keep the page's
    refinement on release (off here unless asked: the benchmarks and tests compare the frames the
    blend makes).
    """
    import re
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "mitsuba_manifold.apps.cli.explore", "--port", "0"]
    for b in bases:
        cmd += ["--basis", os.fspath(b)]
    if manifold:
        cmd += ["--manifold", os.fspath(manifold)]
    if not refine:
        cmd += ["--refine-spp", "0"]
    proc = subprocess.Popen(
        cmd + list(extra), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        found = re.search(r"explore at (http://\S+)", line)
        if found:
            return proc, found.group(1)
    proc.kill()
    raise RuntimeError("explore server did not start:\n" + "".join(lines))


def stop(proc, timeout=20):
    """Ctrl-C (SIGINT) the server; returns its exit code and remaining output."""
    import signal

    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except Exception:
        proc.kill()
        out, _ = proc.communicate()
    return proc.returncode, out
