"""Helpers of the fault tests: run a tool's main(argv) in-process, snapshot folders."""

import contextlib
import hashlib
import importlib
import importlib.util
import io
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_MODULES = {}


def tool_module(name):
    """The module holding tool ``name``'s ``main(argv)``: ``mitsuba_manifold.apps.cli.<name>``
    when the package has it, else ``tools/<name>.py`` loaded as the script is."""
    if name not in _MODULES:
        try:
            _MODULES[name] = importlib.import_module(f"mitsuba_manifold.apps.cli.{name}")
        except ModuleNotFoundError:
            tools = os.path.join(ROOT, "tools")
            if tools not in sys.path:
                sys.path.insert(0, tools)
            spec = importlib.util.spec_from_file_location(
                f"_tool_{name}", os.path.join(tools, name + ".py")
            )
            mod = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(mod)
            _MODULES[name] = mod
    return _MODULES[name]


def run_tool(name, *args):
    """``(exit code, stdout, stderr)`` of ``tools/<name>.py args`` run in this process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = tool_module(name).main([str(a) for a in args])
        except SystemExit as e:
            rc = e.code
    rc = 0 if rc is None else (rc if isinstance(rc, int) else 1)
    return rc, out.getvalue(), err.getvalue()


def error_lines(stderr):
    """Lines of ``stderr`` that report an error."""
    return [line for line in stderr.splitlines() if "error:" in line.lower()]


def assert_one_error(rc, stderr, *words):
    """Exit 2, exactly one ``error:`` line, no traceback, and the line names ``words``."""
    lines = error_lines(stderr)
    assert rc == 2, (rc, stderr)
    assert "Traceback" not in stderr, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    for w in words:
        assert w.lower() in lines[0].lower(), (w, lines[0])
    return lines[0]


def snapshot(folder):
    """{relative path: (sha256, mode)} of every file under ``folder``."""
    out = {}
    for dirpath, _, files in os.walk(folder):
        for f in files:
            p = os.path.join(dirpath, f)
            with open(p, "rb") as fh:
                digest = hashlib.sha256(fh.read()).hexdigest()
            out[os.path.relpath(p, folder)] = (digest, os.stat(p).st_mode)
    return out


SPHERE = os.path.join(ROOT, "scenes", "sphere.xml")
TINY_NAMES = ["steel", "chrome", "gold-paint", "pink-fabric"]
#: Table resolution of the tiny databases.
DIMS = (8, 8, 16)


def render_basis_args(manifold, out, *extra, scene=SPHERE, res=8, spp=1):
    """The command line (strings) of a small ``render_basis`` run: ``scene`` with ``manifold``
    into ``out`` at ``res`` pixels and ``spp`` samples (None: the tool's default), then ``extra``.
    """
    args = [scene, "--manifold", manifold, "--out", out, "--res", res]
    args += [] if spp is None else ["--spp", spp]
    return [str(a) for a in [*args, *extra]]


def render_basis_command(manifold, out, *extra, **options):
    """:func:`render_basis_args` as the command that runs ``tools/render_basis.py`` in a new process."""
    script = os.path.join(ROOT, "tools", "render_basis.py")
    return [sys.executable, script, *render_basis_args(manifold, out, *extra, **options)]


def run_render_basis(manifold, out, *extra, **options):
    """``(exit code, stdout, stderr)`` of ``render_basis`` run on :func:`render_basis_args`."""
    return run_tool("render_basis", *render_basis_args(manifold, out, *extra, **options))


def write_table(path, dims=DIMS, value=1.0):
    """A MERL table of ``dims`` bins, every value ``value``."""
    import numpy as np

    from mitsuba_manifold.data import merl

    merl.write_binary(path, np.full((3,) + tuple(dims), value))


def make_tiny(root):
    """A 4-material database at 8x8x16, a q=2 manifold on it and an 8x8 basis of the
    sphere scene rendered by render_basis.py, under ``root``; returns their paths."""
    from mitsuba_manifold.data import database
    from mitsuba_manifold.manifold.model import Manifold

    db, m, basis = root / "db", root / "manifold.npz", root / "basis"
    database.make_database(db, (8, 8, 16), TINY_NAMES)
    Manifold.fit(str(db), q=2).save(m)
    rc, _, err = run_render_basis(m, basis, "--mode", "per-material")
    assert rc == 0, err
    return {"root": root, "db": str(db), "manifold": str(m), "basis": str(basis)}


def refused_cleanly(rc, stderr, before, folders):
    """For a failed run (rc != 0): exit 2, one error line, and ``snapshot`` of every folder
    as ``before``; returns False for a successful run (nothing checked)."""
    if rc == 0:
        return False
    assert_one_error(rc, stderr)
    assert [snapshot(f) for f in folders] == before
    return True
