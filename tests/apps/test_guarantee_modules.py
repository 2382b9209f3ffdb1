"""The modules behind the guarantees (issue 10), without rendering: locks, ownership,
validators, content identity, render passes."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from mitsuba_manifold._util import checks as validate
from mitsuba_manifold._util import ownership
from mitsuba_manifold._util.locking import FolderLock
from mitsuba_manifold.data import merl
from mitsuba_manifold.errors import FolderLockedError, ForeignFileError, InputError
from mitsuba_manifold.manifold.file import identity
from mitsuba_manifold.manifold.file.fit_record import FitRecord
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.jobs import interrupt


def test_folder_lock_is_exclusive_adds_no_file_and_is_released(tmp_path):
    folder = tmp_path / "f"
    with FolderLock(folder, "basis folder"):
        with pytest.raises(FolderLockedError, match="basis folder .* another process"):
            FolderLock(folder, "basis folder").acquire()  # another open file description
        assert os.listdir(folder) == []
    with FolderLock(folder):  # released
        pass


_LOCKER = """
import os, sys
from mitsuba_manifold._util.locking import FolderLock
folder, n = sys.argv[1], int(sys.argv[2])
inside = os.path.join(folder, "inside")
for _ in range(n):
    with FolderLock(folder, name="count.lock", wait=True):
        os.close(os.open(inside, os.O_CREAT | os.O_EXCL))  # fails if the other is inside too
        path = os.path.join(folder, "count")
        count = int(open(path).read()) if os.path.exists(path) else 0
        open(path, "w").write(str(count + 1))
        os.unlink(inside)
"""


def test_a_lock_file_is_removed_on_release_and_still_excludes(tmp_path):
    """A named lock's file goes with the lock, also when the block fails, and two processes
    taking and releasing it in turn are never inside together (an acquirer that locked the
    file just removed locks the new one).
    """
    folder = tmp_path / "f"
    lock = FolderLock(folder, "output folder", name="x.lock")
    with lock:
        assert os.listdir(folder) == ["x.lock"]
        with pytest.raises(FolderLockedError, match="output folder .* another process"):
            FolderLock(folder, "output folder", name="x.lock").acquire()
    assert os.listdir(folder) == []
    with pytest.raises(KeyError), FolderLock(folder, name="x.lock"):
        raise KeyError("a failed run")
    assert os.listdir(folder) == []
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _LOCKER, str(folder), "300"], cwd=root, stderr=subprocess.PIPE
        )
        for _ in range(2)
    ]
    errors = [p.communicate(timeout=120)[1].decode() for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errors
    assert (folder / "count").read_text() == "600" and os.listdir(folder) == ["count"]


def test_ownership_of_single_outputs(tmp_path):
    out = tmp_path / "img.exr"
    ownership.check_replaceable(out)  # new file: fine
    out.write_bytes(b"one")
    with pytest.raises(ForeignFileError, match="not written by this tool.*pass `force`"):
        ownership.check_replaceable(out)
    ownership.check_replaceable(out, force=True)
    ownership.record([out], "test")
    ownership.check_replaceable(out)  # its own output
    out.write_bytes(b"edited by the user")
    with pytest.raises(ForeignFileError, match="changed since"):
        ownership.check_replaceable(out)
    ownership.record([out], "test")
    os.chmod(out, 0o444)
    with pytest.raises(ForeignFileError, match="read-only"):
        ownership.check_replaceable(out, force=True)
    with pytest.raises(ForeignFileError, match="is a folder"):
        ownership.check_replaceable(tmp_path)
    with pytest.raises(ForeignFileError, match="is a file, not a folder"):
        ownership.check_replaceable(out / "x.exr")


@pytest.mark.parametrize(
    "value, ok",
    [
        (0, True),
        (-64, True),
        (64, True),
        (64.5, False),
        (float("nan"), False),
        (float("inf"), False),
        ("abc", False),
        (1e10, False),
    ],
)
def test_exposure_validator(value, ok):
    if ok:
        assert validate.exposure(value) == float(value)
    else:
        with pytest.raises(
            InputError, match="^`exposure` must be"
        ):  # a Python parameter, not an option
            validate.exposure(value)


def test_resolution_validator_names_the_limit_and_the_memory(monkeypatch):
    assert merl.table_resolution((90, 90, 180)) == (90, 90, 180)
    with pytest.raises(InputError, match="not read by this package"):
        merl.table_resolution((100000, 100000, 100000))
    monkeypatch.setattr(validate, "available_memory", lambda: 1 << 30)
    with pytest.raises(InputError, match="GiB"):
        merl.table_resolution((256, 256, 512))


def test_memory_refusal_states_the_margin_it_applies(monkeypatch):
    monkeypatch.setattr(validate, "available_memory", lambda: int(21.1 * 2**30))
    validate.fits_in_memory("--steps", int(16.8 * 2**30), "images")  # under 80%: accepted
    with pytest.raises(InputError) as e:
        validate.fits_in_memory("--steps", int(20.6 * 2**30), "100000 images of 1024x1024")
    text = str(e.value)
    assert (
        "20.6 GiB" in text
        and "at most 80% of the 21.1 GiB available" in text
        and "(16.9 GiB)" in text
    )
    assert "GiB are available" not in text


def test_weight_sum_is_exact_and_refuses_cancellation():
    with pytest.raises(InputError, match="sum to 1 but their magnitudes"):  # fsum: exactly 1, not 0
        validate.weight_sum([1e11, -1e11, 1.0])
    with pytest.raises(InputError, match="sum to zero"):
        validate.weight_sum([1.0, -1.0])
    assert validate.weight_sum([0.3, 0.7]) == pytest.approx(1.0)


def test_identity_is_the_content_not_the_file(small_manifold, tmp_path):
    m = Manifold.load(small_manifold)
    copy = Manifold(
        m.names,
        m.latent.copy(),
        "/elsewhere",
        m.hashes,
        m.length_scale,
        m.noise,
        m.features,
        record=FitRecord.from_info({"time_fit_s": 123.0}, [1.0, 2.0]),
    )
    assert identity.manifold_identity(copy) == identity.manifold_identity(m)
    moved = m.latent.copy()
    moved[0, 0] = np.nextafter(moved[0, 0], np.inf)
    other = Manifold(m.names, moved, m.database, m.hashes, m.length_scale, m.noise, m.features)
    assert identity.manifold_identity(other) != identity.manifold_identity(m)


@pytest.mark.parametrize(
    "spp, pixels", [(1, 10), (64, 256 * 256), (1000, 1), (7, 1 << 21), (4096, 32 * 32)]
)
def test_render_passes_split_the_samples(spp, pixels):
    passes = interrupt.sample_passes(spp, pixels)
    assert sum(passes) == spp and all(n >= 1 for n in passes)
    assert all(n * pixels <= interrupt.SAMPLES_PER_PASS for n in passes) or passes == [1] * spp


def test_a_stop_request_gets_ctrl_c_again_after_a_render_replaced_its_handler():
    """A render may leave another SIGINT handler installed (Mitsuba's own passes the signal on
    to the one it found): before each pass the request installs its handler again, so Ctrl-C
    still sets the flag; leaving restores the handler found on entering."""
    import signal

    before = signal.getsignal(signal.SIGINT)
    with interrupt.StopRequest() as stop:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # what a render left behind
        stop.rearm()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs in the main thread between bytecodes
        assert stop.requested
        with pytest.raises(KeyboardInterrupt):
            stop.check()
    assert signal.getsignal(signal.SIGINT) is before
    with interrupt.StopRequest() as stop:  # a check between passes re-arms it too
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        stop.check()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert stop.requested
