"""The folder tree is the architecture: dependencies point one way, no import cycle (imports
inside functions counted), Mitsuba and Dr.Jit only in the rendering subsystem and the apps."""

import ast
import os

import mitsuba_manifold

PACKAGE = os.path.dirname(mitsuba_manifold.__file__)
NAME = "mitsuba_manifold"

#: Subsystem -> rank: a module may import only subsystems of a lower rank, or its own.
RANKS = {
    "errors": 0,
    "_util": 1,
    "data": 2,
    "gp": 2,
    "imaging": 2,
    "manifold": 3,
    "basis": 4,
    "render": 5,
    "apps": 6,
}
RENDERING = ("render", "apps")


def _modules():
    found = {}
    for folder, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(folder, f)
                rel = os.path.relpath(path, os.path.dirname(PACKAGE))[:-3].replace(os.sep, ".")
                found[rel[: -len(".__init__")] if rel.endswith(".__init__") else rel] = path
    return found


def _imports(module, path, modules):
    """(imported package modules, imports Mitsuba/Dr.Jit) of ``module``, anywhere in its body."""
    is_package = path.endswith("__init__.py")
    here = module.split(".") if is_package else module.split(".")[:-1]
    deps, heavy = set(), False
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.Import):
            for a in node.names:
                heavy |= a.name.split(".")[0] in ("mitsuba", "drjit")
                if a.name.startswith(NAME + "."):
                    deps.add(a.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
                heavy |= target.split(".")[0] in ("mitsuba", "drjit")
            if target == NAME or target.startswith(NAME + "."):
                for a in node.names:
                    deps.add(f"{target}.{a.name}" if f"{target}.{a.name}" in modules else target)
    return {d for d in deps if d in modules and d != module}, heavy


def _graph():
    modules = _modules()
    return modules, {m: _imports(m, p, modules) for m, p in modules.items()}


def _subsystem(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_no_import_cycle_even_through_imports_inside_functions():
    modules, graph = _graph()
    edges = {m: deps for m, (deps, _) in graph.items()}
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(edges[m]):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d) :] + [d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_dependencies_point_one_way_between_subsystems():
    modules, graph = _graph()
    wrong = []
    for m, (deps, _) in graph.items():
        mine = _subsystem(m)
        if mine is None:  # the package face imports lazily, by name, on first use
            assert not deps, f"{m} imports {sorted(deps)} at import time"
            continue
        for d in deps:
            theirs = _subsystem(d)
            if theirs is not None and theirs != mine and RANKS[theirs] >= RANKS[mine]:
                wrong.append(f"{m} -> {d}")
    assert not wrong, "imports against the layering: " + ", ".join(sorted(wrong))


def test_only_the_rendering_subsystem_and_the_apps_import_mitsuba():
    modules, graph = _graph()
    heavy = sorted(m for m, (_, h) in graph.items() if h and _subsystem(m) not in RENDERING)
    assert not heavy, f"modules outside render/ and apps/ importing Mitsuba or Dr.Jit: {heavy}"


def test_every_subsystem_has_a_rank():
    assert {_subsystem(m) for m in _modules()} - {None} <= set(RANKS)


#: The benchmarks: top-level, beside the package and outside the wheel.
BENCHMARKS = os.path.join(os.path.dirname(PACKAGE), "benchmarks")
TESTS = os.path.dirname(os.path.abspath(__file__))


def _top_level_imports(path):
    """Top-level names of the modules that ``path`` imports absolutely, anywhere in its body."""
    names = set()
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


def _python_files(folder):
    for dirpath, _, files in os.walk(folder):
        yield from (os.path.join(dirpath, f) for f in files if f.endswith(".py"))


def test_the_benchmarks_use_the_package_and_the_package_never_the_benchmarks():
    """Benchmarks import the package (absolutely: they are not part of it); nothing in the
    package imports them, and only the benchmarks' own tests (tests/bench) do."""
    assert os.path.isfile(os.path.join(BENCHMARKS, "__init__.py"))
    assert not os.path.exists(os.path.join(PACKAGE, "apps", "bench"))
    users = [p for p in _python_files(BENCHMARKS) if NAME in _top_level_imports(p)]
    assert len(users) > 10
    wrong = [
        os.path.relpath(p, PACKAGE)
        for p in _python_files(PACKAGE)
        if "benchmarks" in _top_level_imports(p)
    ]
    assert not wrong, f"package modules importing the benchmarks: {wrong}"
    bench_tests = os.path.join(TESTS, "bench")
    wrong = [
        os.path.relpath(p, TESTS)
        for p in _python_files(TESTS)
        if not p.startswith(bench_tests + os.sep) and "benchmarks" in _top_level_imports(p)
    ]
    assert not wrong, (
        f"core tests importing the benchmarks (put benchmark tests in tests/bench): {wrong}"
    )
