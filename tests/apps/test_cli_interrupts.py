"""Ctrl-C at any moment of a command-line tool: one line and exit 130, also when the interrupt
cuts an import half-way (which surfaces as another exception), and exit 0 when it comes after
everything was written."""

import signal

from helpers import run_python


def _run(code):
    """Run ``code`` in a fresh Python process that imports ``guarded``: (returncode, stderr)."""
    rc, _, err = run_python(code, "from mitsuba_manifold.apps.cli.common import guarded")
    return rc, err


def test_ctrl_c_that_cuts_an_import_is_reported_as_an_interrupt():
    """Ctrl-C while an extension imports: the module's own error handling turns it into a NameError
    (as Dr.Jit's __init__ does); the tool reports the interrupt in one line."""
    rc, err = _run("""
        def work(argv=None):
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1)
            except BaseException:
                pass
            return _drjit_ext.__file__
        sys.exit(guarded(work)())
    """)
    assert rc == 130, err
    assert err.startswith("error: interrupted") and err.strip().count("\n") == 0, err


def test_ctrl_c_after_everything_was_written_exits_0():
    rc, err = _run("""
        result = guarded(lambda argv=None: 0)()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)
        sys.exit(result)
    """)
    assert rc == 0 and err == "", err


def test_an_in_process_call_keeps_the_callers_ctrl_c():
    from mitsuba_manifold.apps.cli.common import guarded

    before = signal.getsignal(signal.SIGINT)
    assert guarded(lambda argv=None: 0)([]) == 0
    assert signal.getsignal(signal.SIGINT) is before
