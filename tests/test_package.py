"""The package face and its plumbing: lazy imports, self-registering plugins, one root exception,
thin tools, module sizes."""

import ast
import importlib
import inspect
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


#: Most statements of a function whose docstring does not say why it is long (statements, not
#: lines: the count does not depend on the formatter). Modules have no cap: a module holds one
#: concept, however long that is.
MAX_FUNCTION_STATEMENTS = 70
#: A docstring saying why its function is long ("long because ...", "it stays long: ..."),
#: not "as long as".
SAYS_WHY_LONG = re.compile(r"(?<!as )\blong\b(?! as)", re.IGNORECASE)


def _sources():
    for folder, _, files in os.walk(PACKAGE):
        for f in sorted(files):
            if f.endswith(".py"):
                path = os.path.join(folder, f)
                yield (
                    os.path.relpath(path, os.path.dirname(PACKAGE)),
                    open(path, encoding="utf-8").read(),
                )


def test_functions_are_short_enough_to_read_at_once():
    """No function over 70 statements unless its docstring says why (the path tracer's loop may
    stay long, as Mitsuba's ``prb.sample`` does)."""
    long_functions = []
    for rel, text in _sources():
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = _statements(node)
                if length > MAX_FUNCTION_STATEMENTS and not SAYS_WHY_LONG.search(
                    ast.get_docstring(node) or ""
                ):
                    long_functions.append(f"{rel}:{node.lineno} {node.name} ({length} statements)")
    assert not long_functions, (
        f"functions over {MAX_FUNCTION_STATEMENTS} statements whose docstring does not say why: "
        f"{long_functions}"
    )


def _statements(function):
    """Statements in a function's body, nested ones included (its docstring not counted)."""
    return (
        sum(isinstance(n, ast.stmt) for n in ast.walk(function))
        - 1
        - bool(ast.get_docstring(function))
    )


def test_the_size_check_finds_long_code():
    """The check above can fail: it counts a long function, and reads a docstring's reason."""
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_STATEMENTS + 1))
    tree = ast.parse(f'def f():\n    """Short."""\n{body}\n')
    (f,) = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)]
    assert _statements(f) == MAX_FUNCTION_STATEMENTS + 1
    assert not SAYS_WHY_LONG.search(ast.get_docstring(f))
    assert SAYS_WHY_LONG.search("The loop is long because each bounce updates six states.")
    assert not SAYS_WHY_LONG.search("Iterates as long as the error drops.")


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


#: Most parameters of a package function (``self``/``cls`` not counted, ``*args``/``**kwargs``
#: counted once each) before it needs a parameter object, or a reason in its docstring.
MAX_PARAMETERS = 10
#: Package functions allowed that many parameters; each says why in its docstring. The list only
#: shrinks: a new long signature takes a parameter object instead.
LONG_SIGNATURES = {
    "basis/blend.py:blend_path",  # nine named parameters and **overrides, as match's settings
    "manifold/model.py:Manifold.__init__",
    "manifold/model.py:Manifold.fit",
    "render/scene/references.py:render_reference",
}


def _signatures():
    """``{"path:Class.function": (parameters, positional)}`` of every function of the package."""
    out = {}
    for folder, _, files in os.walk(PACKAGE):
        for f in files:
            if not f.endswith(".py"):
                continue
            path = os.path.join(folder, f)
            rel = os.path.relpath(path, PACKAGE).replace(os.sep, "/")
            tree = ast.parse(open(path).read())
            classes = {
                id(fn): c.name
                for c in ast.walk(tree)
                if isinstance(c, ast.ClassDef)
                for fn in c.body
            }
            for fn in ast.walk(tree):
                if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    a = fn.args
                    positional = [p.arg for p in a.posonlyargs + a.args]
                    if positional and positional[0] in ("self", "cls"):
                        positional = positional[1:]
                    n = (
                        len(positional)
                        + len(a.kwonlyargs)
                        + (a.vararg is not None)
                        + (a.kwarg is not None)
                    )
                    name = f"{classes[id(fn)]}.{fn.name}" if id(fn) in classes else fn.name
                    out[f"{rel}:{name}"] = (n, len(positional), ast.get_docstring(fn) or "")
    return out


def test_long_signatures_are_few_and_take_keywords():
    """A function of ten or more parameters is one of the listed few (the list only shrinks);
    new ones take a parameter object (a dataclass) instead."""
    signatures = _signatures()
    long = {k for k, (n, _, _) in signatures.items() if n >= MAX_PARAMETERS}
    assert long <= LONG_SIGNATURES, (
        f"new functions of >= {MAX_PARAMETERS} parameters: {sorted(long - LONG_SIGNATURES)}"
    )
    assert not LONG_SIGNATURES - long, (
        f"no longer long, drop from the list: {sorted(LONG_SIGNATURES - long)}"
    )


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
