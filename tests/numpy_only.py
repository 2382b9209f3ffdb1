"""A pytest plugin that holds ``-m "not render"`` to its word: a session whose marker expression
deselects the ``render`` tests fails when Mitsuba, Dr.Jit or Ray was imported by the end of it
(by a test module, a fixture, or the library code a test called).

``tests/conftest.py`` loads it for the suite; ``-p numpy_only`` (with ``tests/`` on the path)
loads it for any other folder of tests.
"""

import re
import sys

import pytest

#: What a NumPy-only session must not start.
HEAVY = ("mitsuba", "drjit", "ray")


def excludes_render(config):
    """True when the session's ``-m`` expression deselects the ``render`` marker."""
    return re.search(r"\bnot\s+render\b", config.getoption("markexpr", "") or "") is not None


def pytest_sessionfinish(session, exitstatus):
    if not excludes_render(session.config):
        return
    loaded = [m for m in HEAVY if m in sys.modules]
    if loaded:
        print(
            f'\nerror: -m "not render" imported {", ".join(loaded)}: mark the tests that need them '
            "with @pytest.mark.render and import them inside those tests",
            file=sys.stderr,
        )
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
