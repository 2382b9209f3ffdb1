"""Markers that tell the truth: ``-m "not render"`` is the NumPy-only part of the suite and
starts neither Mitsuba, Dr.Jit nor Ray (:mod:`numpy_only` fails such a session when it does)."""

import os
import subprocess
import sys

import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(TESTS)
#: The subsystems whose tests need no renderer (their rendering tests carry the ``render`` marker).
NUMPY_ONLY = ("data", "gp", "manifold", "imaging", "basis", "util")


def _pytest(*args, cwd=ROOT):
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([ROOT, TESTS, os.environ.get("PYTHONPATH", "")])
    )
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=600,
    )


def test_a_numpy_only_session_that_imports_mitsuba_fails(tmp_path):
    """The check itself: an unmarked test importing Mitsuba fails the ``not render`` session,
    the same test marked ``render`` is deselected and the session passes."""
    pytest.importorskip("mitsuba")
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    render: renders\n")
    test = tmp_path / "test_sneaky.py"
    test.write_text("def test_numpy_only():\n    import mitsuba  # noqa: F401\n")
    r = _pytest("-p", "numpy_only", "-m", "not render", str(test), cwd=tmp_path)
    assert r.returncode == 1 and "imported mitsuba" in r.stderr, r.stdout + r.stderr
    assert "1 passed" in r.stdout  # the test passed: the session failed because of what it imported
    test.write_text(
        "import pytest\n\n@pytest.mark.render\ndef test_renders():\n    import mitsuba  # noqa: F401\n"
    )
    r = _pytest("-p", "numpy_only", "-m", "not render", str(test), cwd=tmp_path)
    assert r.returncode == 5 and "imported" not in r.stderr, (
        r.stdout + r.stderr
    )  # 5: nothing left to run


def test_collecting_the_numpy_only_subsystems_imports_no_renderer():
    """Every test module of the NumPy-only subsystems imports without Mitsuba, Dr.Jit or Ray
    (their rendering tests import them inside the test). Running them,
    ``pytest -m "not render" tests/{data,gp,manifold,imaging,basis,util}``, is checked the same
    way by the suite's conftest."""
    r = _pytest(
        "--collect-only", "-m", "not render", *(os.path.join("tests", s) for s in NUMPY_ONLY)
    )
    assert r.returncode == 0 and "imported" not in r.stderr, r.stdout[-3000:] + r.stderr[-3000:]
    assert " tests collected" in r.stdout or "selected" in r.stdout, r.stdout[-2000:]
