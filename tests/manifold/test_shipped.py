"""The shipped manifolds: each the default fit of its built-in set, loaded by name wherever a
manifold file is taken; a bare name where a path of that name exists is refused as ambiguous
(the rule of database names), ``builtin:NAME`` and ``./NAME`` say which."""

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mitsuba_manifold import Manifold
from mitsuba_manifold.data.database import Database
from mitsuba_manifold.errors import InputError
from mitsuba_manifold.manifold import presets
from mitsuba_manifold.manifold.file.shipped import SHIPPED, resolve_manifold, shipped_path

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.parametrize("name", list(SHIPPED))
def test_each_shipped_manifold_is_the_default_fit_of_its_set(name):
    m = Manifold.load(name)
    assert m.file == shipped_path(name) and m.database == name
    assert m.names == Database(name).names  # every material of the set, in its order
    cfg = presets.settings("default")
    assert m.q == cfg["q"] and m.features == cfg["features"]
    assert m.info.get("preset") == "default"
    assert os.path.getsize(shipped_path(name)) < 1_000_000
    assert np.isfinite(m.latent).all() and len(np.unique(m.latent.round(6), axis=0)) == m.n


def test_the_default_is_merl_with_its_materials_by_name():
    m = Manifold.load("merl")
    assert m.n == 100 and m.q == 4
    np.testing.assert_array_equal(m.point("gold-paint"), m.latent[m.index("gold-paint")])


def test_a_shipped_name_beside_a_path_of_that_name_is_refused_naming_both(
    tmp_path, small_manifold, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    assert resolve_manifold("merl") == shipped_path("merl")
    shutil.copy(small_manifold, tmp_path / "merl")
    with pytest.raises(InputError, match=r"'merl' is ambiguous.*say \./merl.*builtin:merl"):
        resolve_manifold("merl")
    with pytest.raises(InputError, match="ambiguous"):
        Manifold.load("merl")
    assert resolve_manifold("./merl") == "./merl"
    assert Manifold.load("./merl").n == Manifold.load(small_manifold).n
    assert resolve_manifold("builtin:merl") == shipped_path("merl")
    assert resolve_manifold("merl", recorded=True) == shipped_path("merl")
    assert resolve_manifold("no-such.npz") == "no-such.npz"  # the reader says it is missing
    with pytest.raises(InputError, match=r"no-such\.npz does not exist.*merl, rgl, nielsen, all"):
        Manifold.load("no-such.npz")
    with pytest.raises(InputError, match="no shipped manifold 'sgd'"):
        shipped_path("sgd")
    with pytest.raises(InputError, match="no shipped manifold 'sgd'"):
        resolve_manifold("builtin:sgd")


def test_the_package_data_holds_the_shipped_manifolds():
    """pyproject's package data carries every shipped manifold (a wheel built with
    ``pip wheel .`` holds ``mitsuba_manifold/manifold/shipped/*.npz``), together under 1.5 MB."""
    text = open(os.path.join(ROOT, "pyproject.toml"), encoding="utf-8").read()
    assert re.search(r'^"mitsuba_manifold\.manifold" = \["shipped/\*\.npz"\]$', text, re.M)
    paths = [shipped_path(name) for name in SHIPPED]
    assert all(os.path.dirname(p).endswith(os.path.join("manifold", "shipped")) for p in paths)
    assert sum(os.path.getsize(p) for p in paths) < 1_500_000


@pytest.mark.render
def test_the_plugin_and_the_tools_take_a_shipped_name(tmp_path, variant):
    import mitsuba as mi

    bsdf = mi.load_dict({"type": "manifold_brdf", "manifold": "merl", "material": "steel"})
    assert os.path.samefile(bsdf.manifold_path, shipped_path("merl"))
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(
        [sys.executable, os.path.join(ROOT, "tools", "project.py"), "nielsen:notebook"]
        + ["--manifold", "nielsen"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0 and "nearest training material notebook" in r.stdout, r.stderr


def test_build_manifolds_refits_a_shipped_manifold_byte_for_byte(tmp_path):
    """tools/build_manifolds.py writes the default fit of a set; twice the same bytes (no wall
    times, fixed archive dates), and the points of the shipped file."""
    from mitsuba_manifold.apps.cli import build_manifolds

    for out in ("a", "b"):
        build_manifolds.main(["--sets", "nielsen", "--out", str(tmp_path / out)])
    a, b = (tmp_path / out / "nielsen.npz" for out in ("a", "b"))
    assert a.read_bytes() == b.read_bytes()
    m = Manifold.load(a)
    assert m.record.timings.fit_s is None and m.n == 8
    np.testing.assert_allclose(m.latent, Manifold.load("nielsen").latent, atol=1e-4)
    with pytest.raises(SystemExit):
        build_manifolds.main(["--sets", "sgd", "--out", str(tmp_path / "c")])
