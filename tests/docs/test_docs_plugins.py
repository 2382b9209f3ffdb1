"""The plugin reference (docs/reference/plugins.md) against the plugins themselves.

Every parameter a plugin reads is in its table, every parameter in the table is one Mitsuba
accepts (Mitsuba refuses a property no plugin read), the documented defaults are the ones the
plugin uses, and the "traverse" and "∂" columns are what ``mi.traverse`` reports.
"""

import ast
import inspect
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PAGE = os.path.join(ROOT, "docs", "reference", "plugins.md")

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]


def tables():
    """``{plugin: {parameter: row}}`` of the page, a row a dict of its columns."""
    text = open(PAGE, encoding="utf-8").read()
    out = {}
    for m in re.finditer(r"<!-- table: (\w+) -->\n((?:\|.*\n)+)", text):
        lines = [ln.strip().strip("|").split("|") for ln in m.group(2).strip().splitlines()]
        head = [c.strip() for c in lines[0]]
        rows = {}
        for cells in lines[2:]:
            row = dict(zip(head, (c.strip() for c in cells)))
            rows[row["Parameter"].strip("`")] = row
        out[m.group(1)] = rows
    return out


def read_keys(*modules):
    """Property names a plugin's source reads: ``props.get("k")``, ``props["k"]``, ``"k" in props``
    and helpers called as ``f(props, "k", ...)``."""
    keys = set()
    for module in modules:
        tree = ast.parse(inspect.getsource(module))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                f = node.func
                if (
                    isinstance(f, ast.Attribute)
                    and f.attr == "get"
                    and isinstance(f.value, ast.Name)
                    and f.value.id == "props"
                    and node.args
                    and isinstance(node.args[0], ast.Constant)
                ):
                    keys.add(node.args[0].value)
                if (
                    len(node.args) > 1
                    and isinstance(node.args[0], ast.Name)
                    and node.args[0].id == "props"
                    and isinstance(node.args[1], ast.Constant)
                    and isinstance(node.args[1].value, str)
                ):
                    keys.add(node.args[1].value)
            elif (
                isinstance(node, ast.Subscript)
                and isinstance(node.value, ast.Name)
                and node.value.id == "props"
                and isinstance(node.slice, ast.Constant)
            ):
                keys.add(node.slice.value)
            elif (
                isinstance(node, ast.Compare)
                and isinstance(node.left, ast.Constant)
                and isinstance(node.ops[0], ast.In)
                and isinstance(node.comparators[0], ast.Name)
                and node.comparators[0].id == "props"
            ):
                keys.add(node.left.value)
    return keys


def value(row):
    """A value of the parameter's type for loading the plugin with it."""
    return {"integer": 1, "float": 0.02, "boolean": True}.get(row["Type"], None)


def default(row):
    text = row["Default"].strip("`")
    kind = row["Type"]
    if not text or " " in text:
        return None
    if kind == "integer":
        return int(text)
    if kind == "float":
        return float(text)
    if kind == "boolean":
        return text == "true"
    return text


def test_page_has_the_three_plugins():
    assert set(tables()) == {"manifold_brdf", "manifold_path", "manifold_aovs"}


def test_manifold_brdf_parameters(small_manifold):
    import mitsuba as mi

    from mitsuba_manifold.render.plugin import bsdf, material

    rows = tables()["manifold_brdf"]
    read = read_keys(bsdf, material) | set(material.CHOOSERS)
    assert read == set(rows), "documented and read parameters differ"
    base = {"type": "manifold_brdf", "manifold": small_manifold}
    values = {
        "x": "",
        "material": "gold-paint",
        "weights": "gold-paint:0.5, steel:0.5",
        "sampling": "cosine",
        "interpolation": "linear",
        "prune": 0.02,
        "ad_terms": 4,
    }
    from mitsuba_manifold import Manifold

    values["database"] = Manifold.load(small_manifold).database
    for name in rows:
        if name in ("manifold",):
            continue
        d = dict(base, **{name: values[name]})
        if name not in material.CHOOSERS:
            d["x"] = ""
        mi.load_dict(d)  # Mitsuba refuses a property the plugin did not read
    with pytest.raises(Exception, match="unreferenced"):
        mi.load_dict(dict(base, x="", not_a_parameter=1))
    b = mi.load_dict(dict(base, x=""))
    got = {
        "prune": b._options.prune,
        "sampling": b.sampling,
        "interpolation": b.interpolation,
        "ad_terms": b._ad_terms,
    }
    for name, v in got.items():
        assert default(rows[name]) == v, name


def test_manifold_brdf_traverse(small_manifold):
    import drjit as dr
    import mitsuba as mi

    rows = tables()["manifold_brdf"]
    b = mi.load_dict({"type": "manifold_brdf", "manifold": small_manifold, "x": ""})
    params = mi.traverse(b)
    exposed = set(params.keys())
    assert exposed == {n for n, r in rows.items() if r["traverse"].startswith("yes")}
    for n in exposed:
        differentiable = bool(params.flags(n) & mi.ParamFlags.NonDifferentiable) is False
        assert differentiable == (rows[n]["∂"] == "yes") == dr.is_diff_v(mi.Float), n
    for n, r in rows.items():
        if n not in exposed:
            assert r["∂"] == "no", n


@pytest.mark.parametrize("plugin", ["manifold_path", "manifold_aovs"])
def test_integrator_parameters(plugin):
    import mitsuba as mi

    from mitsuba_manifold.render.integrators import aovs, path

    rows = tables()[plugin]
    module = path if plugin == "manifold_path" else aovs
    inherited = {"hide_emitters"}  # read by Mitsuba's SamplingIntegrator
    assert read_keys(module) == set(rows) - inherited
    for name, row in rows.items():
        v = value(row) if row["Type"] != "string" else default(row)
        mi.load_dict({"type": plugin, name: v})
    with pytest.raises(Exception, match="unreferenced"):
        mi.load_dict({"type": plugin, "not_a_parameter": 1})
    obj = mi.load_dict({"type": plugin})
    attrs = {
        "max_depth": lambda o: -1 if o.max_depth == 0xFFFFFFFF else o.max_depth,
        "rr_depth": lambda o: o.rr_depth,
        "component": lambda o: o.component,
        "target": lambda o: o.target,
        "split": lambda o: o.split,
        "bins": lambda o: o.bins,
    }
    for name, row in rows.items():
        if name in attrs:
            assert attrs[name](obj) == default(row), name
        assert row["traverse"] == "no" and row["∂"] == "no", name
    assert len(mi.traverse(obj).keys()) == 0
