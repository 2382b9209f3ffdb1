"""The package face and its plumbing: lazy imports, self-registering plugins, one root exception,
thin tools, module sizes."""

import ast
import importlib
import inspect
import json
import os
import re
import subprocess
import sys

import pytest

import mitsuba_manifold
from mitsuba_manifold import errors

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.dirname(mitsuba_manifold.__file__)


def _python(code, env=None, **kw):
    env = dict(
        os.environ if env is None else env,
        PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
    )
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, **kw
    )


def test_import_is_cheap_and_the_face_is_lazy():
    r = _python(
        "import sys, mitsuba_manifold as mm\n"
        "heavy = [m for m in ('mitsuba', 'drjit', 'numpy', 'scipy') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "from mitsuba_manifold import Manifold, Database, Basis, blend, blend_path, register\n"
        "assert Manifold.__name__ == 'Manifold' and Database.__name__ == 'Database'\n"
        "assert Basis.__name__ == 'Basis' and callable(blend) and blend.__module__.endswith('basis.blend')\n"
        "assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules\n"
        "print('ok')"
    )
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        mitsuba_manifold.nothing  # noqa: B018


def test_every_package_exception_has_the_one_root():
    """No exception class is defined outside errors.py, and every one there has the root."""
    for path, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith(".py") and f != "errors.py":
                tree = ast.parse(open(os.path.join(path, f)).read())
                defined = [
                    n.name
                    for n in ast.walk(tree)
                    if isinstance(n, ast.ClassDef) and n.name.endswith("Error")
                ]
                assert not defined, f"{f} defines {defined}: put exceptions in errors.py"
    classes = [
        c for _, c in inspect.getmembers(errors, inspect.isclass) if issubclass(c, Exception)
    ]
    assert len(classes) > 10 and all(issubclass(c, errors.MitsubaManifoldError) for c in classes)
    assert issubclass(errors.InputError, ValueError) and issubclass(
        errors.UnknownMaterialError, KeyError
    )


def test_tools_are_thin_and_the_cli_reachable():
    for f in os.listdir(os.path.join(ROOT, "tools")):
        if f.endswith(".py"):
            text = open(os.path.join(ROOT, "tools", f)).read()
            entry = "from benchmarks." if f == "bench.py" else "from mitsuba_manifold.apps.cli."
            statements = sum(isinstance(n, ast.stmt) for n in ast.walk(ast.parse(text)))
            assert statements <= 10 and entry in text, f  # a wrapper, whatever its formatting
    from mitsuba_manifold.apps import cli

    for module in cli.TOOLS.values():
        assert callable(importlib.import_module(f"mitsuba_manifold.apps.cli.{module}").main)
    assert cli.main(["--help"]) == 0 and cli.main(["no-such-tool"]) == 2


#: A size rule of ruff (branches, parameters, statements) waived at a function: a ``noqa``
#: comment naming the rule's code, then the reason, on the same line.
SIZE_WAIVER = re.compile(r"#\s*noqa:\s*((?:C901|PLR09\d\d)(?:\s*,\s*[A-Z]+\d+)*)(.*)$")


def test_every_waived_size_rule_says_why_at_the_site():
    """A function over a size limit of the ruff configuration (C901, PLR0913, PLR0915) carries
    ``# noqa`` with its reason beside it: why it is one unit, or why its parameters belong
    together."""
    bare, waived = [], []
    for top in ("mitsuba_manifold", "benchmarks", "tests", "tools", "docs"):
        for folder, _, files in os.walk(os.path.join(ROOT, top)):
            for f in sorted(files):
                if f.endswith(".py"):
                    path = os.path.join(folder, f)
                    for i, line in enumerate(open(path, encoding="utf-8"), 1):
                        m = SIZE_WAIVER.search(line)
                        if m and len(m.group(2).strip()) < 10:
                            bare.append(f"{os.path.relpath(path, ROOT)}:{i}")
                        if m and os.path.basename(path) != "test_package.py":
                            waived.append(f"{os.path.relpath(path, ROOT)}:{i}")
    assert not bare, f"size rules waived without a reason: {bare}"
    pytest.importorskip("ruff")
    found = subprocess.run(  # what the rules find with every waiver ignored
        [sys.executable, "-m", "ruff", "check", "--select", "C901,PLR0913,PLR0915"]
        + ["--ignore-noqa", "--output-format", "json", "--exit-zero", "-q", ROOT],
        capture_output=True,
        text=True,
        check=True,
    )
    over = {
        f"{os.path.relpath(e['filename'], ROOT)}:{e['location']['row']}"
        for e in json.loads(found.stdout)
    }
    stale = sorted(set(waived) - over)
    assert not stale, f"waivers of size rules no function needs now (remove them): {stale}"
    assert SIZE_WAIVER.search("def f(a):  # noqa: C901, PLR0915  one @dr.syntax loop").group(2)
    assert not SIZE_WAIVER.search("x = 1  # noqa: E501")


@pytest.mark.render
def test_readme_blocks_run_in_one_process(small_db, tmp_path):
    """README "Using it": fit and interpolate, then render, in one Python process -- the package
    imported before mi.set_variant, and the plugins there for every variant switched to."""
    code = f"""
from mitsuba_manifold.manifold.model import Manifold
m = Manifold.fit({small_db!r}, q=2)
m.save({str(tmp_path / "manifold.npz")!r})
b, w = m.weights([0.3, -1.2])
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import mitsuba_manifold
from mitsuba_manifold.render.scene.scenes import scene_path
scene = mi.load_file(scene_path("sphere"), manifold={str(tmp_path / "manifold.npz")!r}, x="0.3, -1.2", res="8")
params = mi.traverse(scene); params["material.x"] = [0.5, -1.0]; params.update()
img = mi.render(scene, spp=2)
mi.set_variant("scalar_rgb")
bsdf = mi.load_dict({{"type": "manifold_brdf", "manifold": {str(tmp_path / "manifold.npz")!r}, "material": "chrome"}})
mi.set_variant("llvm_ad_rgb")
integrator = mi.load_dict({{"type": "manifold_path"}})
print("ok", img.shape)
"""
    r = _python(code, timeout=300)
    assert r.returncode == 0 and r.stdout.startswith("ok"), r.stderr[-2000:]


def test_importing_the_package_changes_no_environment_variable():
    """``import mitsuba_manifold`` and its face change nothing, ``os.environ`` included; the rule of
    the package docstring: importing the rendering subsystem selects a libLLVM >= 16 for Dr.Jit."""
    # Third-party libraries may set variables of their own (threadpoolctl: KMP_DUPLICATE_LIB_OK): imported first.
    code = (
        "import os, sys, importlib.util\n"
        "for lib in ('numpy', 'scipy.linalg', 'threadpoolctl'):\n"
        "    if importlib.util.find_spec(lib.split('.')[0]): importlib.import_module(lib)\n"
        "before = dict(os.environ)\n"
        "import mitsuba_manifold\n"
        "from mitsuba_manifold import Manifold, Database, Basis, blend, register, make_database\n"
        "import mitsuba_manifold.basis.folder, mitsuba_manifold.manifold.model, mitsuba_manifold.apps.cli\n"
        "assert dict(os.environ) == before, set(os.environ.items()) ^ set(before.items())\n"
        "assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules\n"
        "print('ok')"
    )
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    r = _python(code, env=env)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
    pytest.importorskip("mitsuba")
    r = _python(
        "import os, mitsuba_manifold.render, mitsuba_manifold.render.plugin.llvm as llvm\n"
        "print(os.environ.get('DRJIT_LIBLLVM_PATH') == llvm.newest())",
        env=env,
    )
    assert r.returncode == 0 and r.stdout.strip() == "True", r.stderr


#: Calls in a test that start Mitsuba (a variant, a render, a scene) or Ray: ``mi.<name>(...)``,
#: ``ray.<name>(...)``, and the package's rendering functions by name.
_MITSUBA = {"set_variant", "render", "load_file", "load_dict"}
_STARTS = {
    "render_basis",
    "render_reference",
    "render_chunked",
    "render_aovs",
    "add_aovs",
    "first_hit_aovs",
    "load_scene",
    "use_variant",
    "register",
    "RayExecutor",
}


def _starts(call):
    f = call.func
    if (
        isinstance(f, ast.Attribute)
        and isinstance(f.value, ast.Name)
        and f.value.id in ("mi", "mitsuba", "ray")
    ):
        return f.attr in _MITSUBA or f.value.id == "ray"
    return getattr(f, "attr", getattr(f, "id", None)) in _STARTS


def _marked_render(decorators):
    return any("render" in ast.unparse(d) for d in decorators)


def test_tests_that_start_mitsuba_or_ray_carry_the_render_marker():
    """``-m "not render"`` is the NumPy-only part: a test that starts Mitsuba or Ray (a call of
    :func:`_starts`, or the ``variant`` fixture) is marked ``render``, itself or its module."""
    unmarked = []
    for folder, _, files in os.walk(os.path.join(ROOT, "tests")):
        for f in sorted(files):
            if not (f.startswith("test_") and f.endswith(".py")):
                continue
            tree = ast.parse(open(os.path.join(folder, f)).read())
            marks = [
                n.value
                for n in tree.body
                if isinstance(n, ast.Assign)
                and any(getattr(t, "id", None) == "pytestmark" for t in n.targets)
            ]
            if _marked_render(marks):
                continue
            for node in tree.body:
                if not (
                    isinstance(node, ast.FunctionDef) and node.name.startswith("test_")
                ) or _marked_render(node.decorator_list):
                    continue
                starts = any(_starts(c) for c in ast.walk(node) if isinstance(c, ast.Call))
                if starts or "variant" in [a.arg for a in node.args.args]:
                    unmarked.append(f"{f}::{node.name}")
    assert not unmarked, f"tests starting Mitsuba or Ray without the render marker: {unmarked}"


def test_negative_latent_coordinates_are_values_not_options():
    """``--near -1.1,-0.2`` (most latent coordinates are negative) parses like ``--near=-1.1,-0.2``."""
    from mitsuba_manifold.apps.cli.common import ArgumentParser, parse_floats

    p = ArgumentParser(prog="t")
    p.add_argument("--near", type=parse_floats)
    p.add_argument("--x", nargs="+")
    p.add_argument("-v", action="store_true")
    assert p.parse_args(["--near", "-1.1,-0.2"]).near == [-1.1, -0.2]
    assert p.parse_args(["--near", "-1e-3 -.5"]).near == [-1e-3, -0.5]
    assert p.parse_args(["--x", "-1", "-2.5", "-v"]).x == ["-1", "-2.5"]
    assert p.parse_args(["-v"]).v
    assert p.parse_args(["--near", "0.3, -1.2"]).near == [0.3, -1.2]
    for text in ("0,,1", "0,1,", ",0"):  # an empty place is a typo, not a shorter point
        with pytest.raises(SystemExit):
            p.parse_args(["--near", text])


def test_console_command_names_the_tool(capsys):
    """``mitsuba-manifold fit --help`` shows ``mitsuba-manifold fit`` in its usage; an unknown
    tool is named in one error line."""
    from mitsuba_manifold.apps import cli

    assert cli.main(["nonsense"]) == 2
    assert "error: unknown tool 'nonsense'" in capsys.readouterr().err
    assert cli.main(["fitt"]) == 2  # a near miss: the tool meant
    assert "unknown tool 'fitt' (did you mean 'fit'?)" in capsys.readouterr().err
    for spelling in ("render_basis", "fit_manifold"):  # the script's name runs its tool
        with pytest.raises(SystemExit):
            cli.main([spelling, "--help"])
        assert f"usage: mitsuba-manifold {cli.ALIASES[spelling]}" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["fit", "--help"])
    assert "usage: mitsuba-manifold fit" in capsys.readouterr().out


#: History in the sources: issue numbers and release notes belong in the CHANGELOG, not the code.
HISTORY = re.compile(r"\bissues? \d+|previous release|earlier release", re.IGNORECASE)


def test_the_sources_state_the_contract_not_the_history():
    """Docstrings and comments say what the code does; no issue numbers or release history."""
    found = []
    for folder, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(folder, f)
                for n, line in enumerate(open(path, encoding="utf-8"), 1):
                    if HISTORY.search(line):
                        found.append(f"{os.path.relpath(path, PACKAGE)}:{n}: {line.strip()[:80]}")
    assert not found, "history in the sources:\n" + "\n".join(found)


#: Most modules (``__init__.py`` counted) in one folder of the package: a folder that grows past
#: it is split into sub-packages, one concept each (render/plugin, render/scene, ...).
MAX_MODULES = 15


def test_no_package_folder_holds_more_than_fifteen_modules():
    crowded = {
        os.path.relpath(folder, PACKAGE): n
        for folder, _, files in os.walk(PACKAGE)
        if (n := sum(f.endswith(".py") for f in files)) > MAX_MODULES
    }
    assert not crowded, (
        f"folders of more than {MAX_MODULES} modules (split them into rooms): {crowded}"
    )


def test_no_module_name_is_used_three_times():
    """A module's name says what it holds: at most two modules of the package share a name; the
    basis folder's format is one package (no ``folder`` beside ``folders``), the fit's record is
    not a near-namesake of the integrators' records."""
    names = {}
    for folder, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith(".py") and f != "__init__.py":
                names.setdefault(f[:-3], []).append(
                    os.path.relpath(os.path.join(folder, f), PACKAGE)
                )
    assert not {n: p for n, p in names.items() if len(p) >= 3}
    assert not ({"folder", "folders"} <= set(names) or {"record", "records"} <= set(names))


def test_one_module_installs_the_ctrl_c_handlers():
    """Only ``_util/interrupts.py`` calls ``signal.signal``: the tools' scripts, the command line,
    the render loops and the worker processes use its calls."""
    calls = set()
    for top in ("mitsuba_manifold", "tools", "benchmarks"):
        for folder, _, files in os.walk(os.path.join(ROOT, top)):
            for f in files:
                if f.endswith(".py"):
                    path = os.path.join(folder, f)
                    for n in ast.walk(ast.parse(open(path, encoding="utf-8").read())):
                        if isinstance(n, ast.Call) and ast.unparse(n.func) == "signal.signal":
                            calls.add(os.path.relpath(path, ROOT).replace(os.sep, "/"))
    assert calls == {"mitsuba_manifold/_util/interrupts.py"}, calls


def test_the_wheel_lists_every_package_folder():
    """Every folder of the package holding an ``__init__.py`` is in ``pyproject.toml``'s explicit
    package list (an editable install hides a missing one; ``pip install .`` would not)."""
    text = open(os.path.join(ROOT, "pyproject.toml"), encoding="utf-8").read()
    listed = set(re.findall(r'^\s*"(mitsuba_manifold[\w.]*)",\s*$', text, re.M))
    found = {
        os.path.relpath(folder, ROOT).replace(os.sep, ".")
        for folder, _, files in os.walk(PACKAGE)
        if "__init__.py" in files
    }
    assert found - listed == set(), f"package folders missing from pyproject.toml: {found - listed}"


def test_test_files_have_unique_names():
    """pytest imports test files by their base name (no packages under ``tests/``): two files
    of one name in different folders stop the whole collection.
    """
    tests = os.path.dirname(os.path.abspath(__file__))
    names = {}
    for folder, _, files in os.walk(tests):
        for f in files:
            if f.startswith("test_") and f.endswith(".py"):
                names.setdefault(f, []).append(os.path.relpath(os.path.join(folder, f), tests))
    assert not {k: v for k, v in names.items() if len(v) > 1}


def test_nothing_beside_the_checkout_is_read():
    """The package and its tests never read a folder beside the checkout (``../shared``): a
    user's clone has nothing beside it (``.ci/run`` runs the suite in such a clone)."""
    pattern = re.compile(
        r"""\.\./shared|/work/shared|["']\.\.["'],\s*["']\.\.["'],\s*["']\.\.["']"""
    )
    for top in ("mitsuba_manifold", "tests", "tools"):
        for folder, _, files in os.walk(os.path.join(ROOT, top)):
            for f in files:
                if f.endswith(".py"):
                    path = os.path.join(folder, f)
                    if path != os.path.abspath(__file__):  # this test names what it looks for
                        assert not pattern.search(open(path, encoding="utf-8").read()), path


#: Least share of public functions and methods with a return annotation (mypy checks them).
MIN_ANNOTATED = 0.8


def _public_functions(tree):
    """Module-level functions and methods (nested classes included) whose names do not start
    with ``_``; functions inside functions are not counted."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if not node.name.startswith("_"):
                yield node
        elif isinstance(node, (ast.ClassDef, ast.If, ast.Try, ast.With)):
            yield from _public_functions(node)


def test_public_functions_say_what_they_return():
    """At least 80% of the package's public functions and methods carry a return annotation."""
    total, missing = 0, []
    for folder, _, files in os.walk(PACKAGE):
        for name in sorted(files):
            if not name.endswith(".py"):
                continue
            path = os.path.join(folder, name)
            rel = os.path.relpath(path, os.path.dirname(PACKAGE))
            with open(path, encoding="utf-8") as f:
                tree = ast.parse(f.read())
            for fn in _public_functions(tree):
                total += 1
                if fn.returns is None:
                    missing.append(f"{rel}:{fn.lineno} {fn.name}")
    share = 1 - len(missing) / total
    assert share >= MIN_ANNOTATED, (
        f"{share:.0%} of {total} public functions have a return annotation, below "
        f"{MIN_ANNOTATED:.0%}; without one: {missing[:20]}"
    )


def test_the_annotation_count_sees_methods_and_skips_inner_functions():
    tree = ast.parse(
        "def a() -> int: ...\n"
        "def b(): ...\n"
        "def _c(): ...\n"
        "class K:\n"
        "    def m(self) -> None:\n"
        "        def inner(): ...\n"
        "    class N:\n"
        "        def n(self): ...\n"
    )
    found = {f.name: f.returns is not None for f in _public_functions(tree)}
    assert found == {"a": True, "b": False, "m": True, "n": False}
