"""Ctrl-C and killed runs (issue 10): a render stops within seconds, every listed file is
complete, no lock is left behind, and the same command resumes.

The tools run as subprocesses: the signals and the operating system are part of the test.
Fixtures: ``tests/apps/conftest.py``.
"""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from guarantees_helpers import (
    ROOT,
    error_lines,
    render_basis_args,
    render_basis_command,
    run_tool,
)

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("plugins")]
mi = pytest.importorskip("mitsuba")
from mitsuba_manifold.imaging import io as imageio  # noqa: E402

# ------------------------------------------------------------ 12. Ctrl-C


def _interrupt_after(proc, wait):
    """Send SIGINT to ``proc`` once ``wait()`` returns; its output, after checking that it
    was still running (``communicate`` fails the test if it has not stopped in 60 s, a guard
    against a hang, not a measured time)."""
    try:
        wait()
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=60)
    finally:
        proc.kill()  # no-op once it has ended
    return out


@pytest.mark.parametrize("mode", ["per-material", "onepass"])
def test_ctrl_c_stops_a_render_within_seconds_leaving_listed_files(tmp_path, tiny, mode):
    out = tmp_path / "basis"
    proc = subprocess.Popen(
        render_basis_command(tiny["manifold"], out, "--mode", mode, res=32, spp=200000),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )

    def wait():
        deadline = time.time() + 120
        while time.time() < deadline and not (out / "manifest.json").exists():
            time.sleep(0.2)
        time.sleep(3.0)  # inside a long render

    _, err = _interrupt_after(proc, wait)
    assert proc.returncode == 130, err
    lines = error_lines(err)
    assert len(lines) == 1 and "interrupted" in lines[0] and "Traceback" not in err, err
    manifest = json.loads((out / "manifest.json").read_text())
    listed = {e["file"] for e in manifest["images"].values()}
    present = {f for f in os.listdir(out) if not f.startswith(".")} - {"manifest.json"}
    assert present == listed
    for f in listed:
        assert imageio.read_exr(out / f).shape == (32, 32, 3)


def test_a_killed_render_leaves_no_lock_and_resumes(tmp_path, tiny):
    out = tmp_path / "basis"
    args = render_basis_args(tiny["manifold"], out, "--mode", "per-material", res=16, spp=3000)
    proc = subprocess.Popen(
        render_basis_command(tiny["manifold"], out, "--mode", "per-material", res=16, spp=3000),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )

    def listed():
        path = out / "manifest.json"
        return json.loads(path.read_text())["images"] if path.exists() else {}

    deadline = time.time() + 120
    while time.time() < deadline and not listed():
        time.sleep(0.1)
    proc.kill()  # kill -9 after the first image (or at the deadline)
    proc.wait()
    before = listed()
    assert before and not [f for f in os.listdir(out) if f.endswith(".tmp")]
    rc, _, err = run_tool("render_basis", *args)  # the lock went with the process; the run resumes
    assert rc == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert set(before) <= set(manifest["images"]) and len(manifest["images"]) == 5
    for entry in manifest["images"].values():
        assert imageio.read_exr(out / entry["file"]).shape == (16, 16, 3)


def test_an_image_written_but_not_yet_listed_is_the_resumed_runs_own(tmp_path, tiny):
    """kill -9 between writing ``<key>.exr`` and listing it: the manifest named it pending,
    so the resume renders it again instead of refusing it as the user's file."""
    out = tmp_path / "basis"
    args = render_basis_args(tiny["manifold"], out, "--mode", "per-material", spp=2)
    assert run_tool("render_basis", *args)[0] == 0
    manifest = json.loads((out / "manifest.json").read_text())
    key = next(k for k in manifest["images"] if k != "base")
    file = manifest["images"].pop(key)["file"]
    manifest["pending"] = [file]
    (out / "manifest.json").write_text(json.dumps(manifest))
    imageio.write_exr(out / file, np.full((8, 8, 3), -7.0, np.float32))  # the killed run's file
    user = out / "notes.exr"
    imageio.write_exr(user, np.zeros((8, 8, 3), np.float32))
    rc, _, err = run_tool("render_basis", *args)
    assert rc == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert key in manifest["images"] and "pending" not in manifest
    assert imageio.read_exr(out / file).min() >= 0  # rendered again
    assert imageio.read_exr(user).shape == (8, 8, 3)  # not ours: untouched
    manifest["images"].pop(key)  # listed nowhere now
    (out / "manifest.json").write_text(json.dumps(manifest))
    rc, _, err = run_tool("render_basis", *args)
    assert rc == 2 and file in err and "did not make" in err


def test_ctrl_c_stops_a_reference_render_and_writes_nothing(tmp_path, tiny):
    out = tmp_path / "blend"
    out.mkdir()
    proc = subprocess.Popen(
        [
            sys.executable,
            os.path.join(ROOT, "tools", "blend.py"),
            "--basis",
            tiny["basis"],
            "--x",
            "0,0",
            "--out",
            str(out / "img.exr"),
            "--render-reference",
            "--spp",
            "1000000",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )

    def wait():  # until the reference render has begun
        for line in proc.stdout:
            if "rendering the reference" in line:
                break
        time.sleep(2.0)

    _, err = _interrupt_after(proc, wait)
    assert proc.returncode == 130, err
    assert len(error_lines(err)) == 1 and "interrupted" in err and "Traceback" not in err, err
    assert os.listdir(out) == []
