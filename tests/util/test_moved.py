"""Modules moved into sub-packages keep their old dotted names: importing one gives the new
module object itself, with a DeprecationWarning naming the new place."""

import importlib
import sys

import pytest

NUMPY_ONLY = [
    ("mitsuba_manifold.basis.match", "mitsuba_manifold.basis.inverse.match"),
    ("mitsuba_manifold.basis.acquisition", "mitsuba_manifold.basis.inverse.acquisition"),
    ("mitsuba_manifold.manifold.search", "mitsuba_manifold.basis.inverse.search"),
    # an old name that is now also a data folder (manifold/shipped/) still finds the module
    ("mitsuba_manifold.manifold.shipped", "mitsuba_manifold.manifold.file.shipped"),
    ("mitsuba_manifold.manifold.io", "mitsuba_manifold.manifold.file.io"),
]
RENDERING = [
    ("mitsuba_manifold.render.scenes", "mitsuba_manifold.render.scene.scenes"),
    ("mitsuba_manifold.render.render_basis", "mitsuba_manifold.render.jobs.render_basis"),
    ("mitsuba_manifold.render.match_scan", "mitsuba_manifold.render.inverse.scan"),
    ("mitsuba_manifold.apps.explore.guard", "mitsuba_manifold.apps.explore.web.guard"),
]


def _import_old(old, new, monkeypatch):
    monkeypatch.delitem(sys.modules, old, raising=False)
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        module = importlib.import_module(old)
    assert module is importlib.import_module(new)
    assert module.__name__ == new
    return module


@pytest.mark.parametrize("old, new", NUMPY_ONLY)
def test_an_old_module_name_imports_the_moved_module(old, new, monkeypatch):
    _import_old(old, new, monkeypatch)


def test_from_imports_of_old_names_work(monkeypatch):
    monkeypatch.delitem(sys.modules, "mitsuba_manifold.basis.targets", raising=False)
    with pytest.warns(DeprecationWarning):
        from mitsuba_manifold.basis.targets import check_mask
    from mitsuba_manifold.basis.inverse.targets import check_mask as new

    assert check_mask is new


def test_names_that_never_existed_still_fail():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("mitsuba_manifold.basis.no_such_module")


@pytest.mark.render
@pytest.mark.parametrize("old, new", RENDERING)
def test_an_old_rendering_module_name_imports_the_moved_module(old, new, monkeypatch):
    if old.startswith("mitsuba_manifold.apps.explore."):
        pytest.importorskip("starlette")
    _import_old(old, new, monkeypatch)
