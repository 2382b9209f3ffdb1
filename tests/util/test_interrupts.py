"""What Ctrl-C does at each stage of a process (``_util/interrupts.py``), in fresh processes:
the signal and the interpreter's exit are part of the test."""

import os
import signal
import threading
import time

import pytest
from helpers import run_python

from mitsuba_manifold._util import interrupts


def _run(code):
    return run_python(code, "from mitsuba_manifold._util import interrupts")


def test_ctrl_c_while_a_tool_starts_is_one_line_and_exit_130():
    rc, out, err = _run("""
        interrupts.exit_while_starting()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)
        print("still running")
    """)
    assert rc == interrupts.INTERRUPTED == 130
    assert err == interrupts.STARTING_MESSAGE + "\n" and out == ""


def test_an_ignoring_process_goes_on_after_ctrl_c():
    rc, out, err = _run("""
        interrupts.ignore()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)
        print("still running")
    """)
    assert rc == 0 and out == "still running\n", err


def test_noted_ctrl_c_raises_and_restores_the_handler_it_replaced():
    before = signal.getsignal(signal.SIGINT)
    noted = interrupts.Noted().install()
    try:
        assert not noted.seen
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the handler runs in the main thread, cutting the sleep
        assert noted.seen
    finally:
        noted.restore()
    assert signal.getsignal(signal.SIGINT) is before


def test_outside_the_main_thread_nothing_is_installed():
    before = signal.getsignal(signal.SIGINT)
    seen = []

    def worker():
        interrupts.ignore()
        interrupts.exit_while_starting()
        noted = interrupts.Noted().install()
        with interrupts.StopRequest() as stop:
            stop.check()
        seen.append((noted.previous, stop.requested))

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen == [(None, False)] and signal.getsignal(signal.SIGINT) is before
