"""The folder tree is the architecture: dependencies point one way, no import cycle (imports
inside functions counted), Mitsuba and Dr.Jit only in the rendering subsystem and the apps."""

import ast
import os

import mitsuba_manifold

PACKAGE = os.path.dirname(mitsuba_manifold.__file__)
NAME = "mitsuba_manifold"

#: Subsystem -> rank: a module may import only subsystems of a lower rank, or its own.
RANKS = {"errors": 0, "_util": 1, "data": 2, "gp": 2, "imaging": 2, "manifold": 3, "basis": 4,
         "render": 5, "apps": 6}
RENDERING = ("render", "apps")


def _modules():
    found = {}
    for folder, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(folder, f)
                rel = os.path.relpath(path, os.path.dirname(PACKAGE))[:-3].replace(os.sep, ".")
                found[rel[:-len(".__init__")] if rel.endswith(".__init__") else rel] = path
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
                base = here[:len(here) - node.level + 1]
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
                cycles.append(stack[stack.index(d):] + [d])
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
        if mine is None:   # the package face imports lazily, by name, on first use
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
