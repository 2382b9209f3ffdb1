"""Kill-safety of make_database (issue 20, item 4): the tool killed (SIGKILL, SIGTERM) at a
hypothesis-drawn moment leaves no process behind, no lock held, and the same command then
finishes with the folder an uninterrupted run makes (no temporary file left)."""

import os
import signal
import subprocess
import sys
import tempfile
import time

import pytest
from guarantees_helpers import ROOT, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mitsuba_manifold._util.atomic import is_temporary

TOOL = [
    sys.executable,
    os.path.join(ROOT, "tools", "make_database.py"),
    "--from",
    "sgd",
    "--resolution",
    "32,32,64",
    "--materials",
    "steel,chrome,gold-paint,pink-fabric,blue-acrylic,black-obsidian",
]  # 32x32x64: big enough for worker processes
ENV = {**os.environ, "PYTHONPATH": ROOT}


def _run(out):
    return subprocess.run(
        TOOL + ["--out", str(out)], env=ENV, capture_output=True, text=True, timeout=300
    )


def _group(pgid):
    """Live processes of process group ``pgid`` (Linux /proc)."""
    alive = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            alive.append(int(pid))
    return alive


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The folder of an uninterrupted run, and the run's wall time."""
    out = tmp_path_factory.mktemp("clean") / "db"
    t0 = time.monotonic()
    done = _run(out)
    assert done.returncode == 0, done.stderr
    return snapshot(out), time.monotonic() - t0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="process groups read from /proc")
@settings(
    max_examples=3, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(moment=st.floats(0.1, 0.9), sig=st.sampled_from([signal.SIGKILL, signal.SIGTERM]))
def test_make_database_killed_at_any_moment_resumes_to_the_same_folder(
    tmp_path, uninterrupted, moment, sig
):
    """``moment``: when the signal comes, as a share of an uninterrupted run's wall time."""
    folder, seconds = uninterrupted
    out = os.path.join(tempfile.mkdtemp(dir=tmp_path), "db")
    proc = subprocess.Popen(
        TOOL + ["--out", out],
        env=ENV,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    time.sleep(moment * seconds)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    deadline = time.monotonic() + 10
    while _group(proc.pid) and time.monotonic() < deadline:  # the workers end with their parent
        time.sleep(0.05)
    assert _group(proc.pid) == []
    again = _run(out)  # not refused: no lock, no foreign table
    assert again.returncode == 0, again.stderr
    assert snapshot(out) == folder
    left = [f for _, _, files in os.walk(out) for f in files if is_temporary(f)]
    assert left == []
