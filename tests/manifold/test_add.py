"""Manifold.add: a measured material placed in a fitted manifold without a refit."""

import json
import os
import shutil
import zipfile

import numpy as np
import pytest
from measured_helpers import MERL, weights_path, write_set

from mitsuba_manifold.data import gram
from mitsuba_manifold.errors import InputError
from mitsuba_manifold.gp.kernel import Kernel
from mitsuba_manifold.gp.likelihood import log_likelihood, log_likelihood_grad
from mitsuba_manifold.gp.placement import OnePoint, place_point
from mitsuba_manifold.manifold.model import Manifold

pytestmark = pytest.mark.skipif(not os.path.exists(weights_path()), reason="no NBRDF weights")


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    root = tmp_path_factory.mktemp("measured")
    merl_db = write_set(str(root / "merl"), "merl", MERL)
    rgl = write_set(str(root / "rgl"), "rgl", ["paper_white", "satin_gold"])
    return merl_db, rgl, Manifold.fit(merl_db)


def test_one_point_likelihood_is_eq6_of_all_points():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(9, 2))
    Z = rng.normal(size=(10, 40))
    Z -= Z.mean(0)
    S = Z @ Z.T
    one = OnePoint(X, S, 40, Kernel(1.0, 1e-3))
    for x in rng.normal(size=(4, 2)):
        L, g = one.value_grad(x)
        L_all, g_all = log_likelihood_grad(np.vstack([X, x]), S, 40, 1.0, 1e-3)
        assert L == pytest.approx(L_all, rel=1e-10)
        assert np.allclose(g, g_all[-1], rtol=1e-7, atol=1e-9 * np.abs(g_all).max())
    p = place_point(X, S, 40, X[:3] + 0.1, noise=1e-3)
    around = [log_likelihood(np.vstack([X, p.x + d]), S, 40, 1.0, 1e-3) for d in 1e-3 * np.eye(2)]
    assert p.log_likelihood >= max(around) - 1e-6 * abs(p.log_likelihood)


def test_add_keeps_the_others_reproduces_the_new_one_and_saves_its_provenance(measured, tmp_path):
    _merl_db, rgl, base = measured
    path = tmp_path / "base.npz"
    base.save(path)
    m = Manifold.load(path)
    before = m.latent.copy()
    m.path(m.names[0], m.names[1], steps=5)  # a path metric of the N materials, kept
    info = m.add(os.path.join(rgl, "paper_white.binary"), origin="rgl:paper_white")
    walk = m.path(m.names[0], "paper_white", steps=5)  # a metric of the N + 1
    assert np.allclose(walk[-1], m.latent[-1])
    assert m.n == base.n + 1 and m.names[-1] == "paper_white" == info.name
    assert np.array_equal(m.latent[:-1], before)  # the others unchanged
    assert np.linalg.norm(m.latent - m.latent[-1], axis=1)[:-1].min() > 1e-6
    tables = m.tables()
    table, keep, _dropped = m.interpolate(m.latent[-1], prune=0.0)
    assert keep.tolist() == [m.n - 1] and np.array_equal(
        table.reshape(-1), tables[-1]
    )  # exact at its point
    for i in range(base.n):  # and the others at theirs
        assert np.array_equal(m.weights(before[i]).w, np.eye(m.n)[i])
    # beyond the hull the weights still continue (the limit belongs to the grown manifold)
    far = m.latent.mean(0) + 3 * (m.latent.max(0) - m.latent.min(0))
    assert np.isclose(m.weights(far).w.sum(), 1.0) and m.weights(far).w.shape == (m.n,)
    # the grown Gram matrices are those of all N + 1 tables
    g = gram.gram(tables, m.features, centre=True, raw=True)
    assert np.allclose(m.gram, g.S, rtol=1e-9, atol=1e-9 * np.abs(g.S).max())
    assert np.allclose(m.table_gram, g.raw, rtol=1e-5)
    # an array is added too (written into the database's cache)
    m.add(tables[-1] * 0.5, name="half-white", origin="half of paper_white")
    out = tmp_path / "added.npz"
    m.save(out)
    with zipfile.ZipFile(out) as z:
        meta = json.loads(str(np.load(z.open("meta.npy"))))
    assert meta["version"] == 3 and [a["name"] for a in meta["added"]] == [
        "paper_white",
        "half-white",
    ]
    again = Manifold.load(out)
    assert [a.origin for a in again.added] == ["rgl:paper_white", "half of paper_white"]
    assert again.added[0].path == os.path.abspath(os.path.join(rgl, "paper_white.binary"))
    assert [a.source for a in again.added] == ["file", "table"]
    assert np.array_equal(again.latent, m.latent)
    assert np.array_equal(again.tables(), m.tables())
    assert np.array_equal(
        again.interpolate(again.latent[-1], prune=0.0)[0].reshape(-1), tables[-1] * 0.5
    )
    with zipfile.ZipFile(path) as z:  # a manifold without added materials stays version 2
        assert json.loads(str(np.load(z.open("meta.npy"))))["version"] == 2


def test_add_refuses_bad_input_before_changing_anything(measured, tmp_path):
    merl_db, _rgl, base = measured
    m = Manifold.load(_saved(base, tmp_path))
    names = list(m.names)
    with pytest.raises(InputError, match="already has a material named 'teflon'"):
        m.add(os.path.join(merl_db, "teflon.binary"))
    with pytest.raises(InputError, match="not a file"):
        m.add(tmp_path / "missing.binary")
    with pytest.raises(InputError, match="values"):
        m.add(np.ones(10), name="x")
    assert m.names == names


def test_an_added_table_that_changed_is_refused(measured, tmp_path):
    _merl_db, rgl, base = measured
    m = Manifold.load(_saved(base, tmp_path))
    copy = tmp_path / "satin.binary"
    shutil.copy(os.path.join(rgl, "satin_gold.binary"), copy)
    m.add(copy, name="satin")
    m.save(tmp_path / "m.npz")
    shutil.copy(os.path.join(rgl, "paper_white.binary"), copy)
    with pytest.raises(InputError, match="'satin' differs"):
        Manifold.load(tmp_path / "m.npz").tables()


def _saved(m, tmp_path):
    path = tmp_path / "base.npz"
    m.save(path)
    return path


def test_fit_manifold_add_places_materials_in_a_saved_manifold(measured, tmp_path, capsys):
    from mitsuba_manifold.apps.cli import fit_manifold

    _merl_db, rgl, base = measured
    saved = _saved(base, tmp_path)
    out = tmp_path / "grown.npz"
    fit_manifold.main(
        [
            str(saved),
            "--out",
            str(out),
            "--add",
            os.path.join(rgl, "paper_white.binary"),
            "--name",
            "white",
            "--add",
            os.path.join(rgl, "satin_gold.binary"),
        ]
    )
    m = Manifold.load(out)
    assert m.names[-2:] == ["white", "satin_gold"] and np.array_equal(m.latent[:-2], base.latent)
    assert [a.name for a in m.added] == ["white", "satin_gold"]
    assert "added white" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        fit_manifold.main([str(saved), "--out", str(tmp_path / "x.npz"), "--name", "a"])


def test_add_to_the_paper_preset_keeps_its_exact_gp_weights(measured, tmp_path):
    merl_db, rgl, _ = measured
    m = Manifold.fit(merl_db, preset="paper")
    before, g_before = m.latent.copy(), m.gram.copy()
    m.add(os.path.join(rgl, "satin_gold.binary"))
    assert m.interpolant.kind == "gp" and m.features == "raw"
    assert np.array_equal(m.latent[:-1], before)
    assert np.array_equal(m.weights(m.latent[-1]).w, np.eye(m.n)[-1])
    for i in range(len(before)):
        assert np.array_equal(m.weights(before[i]).w, np.eye(m.n)[i])
    g = gram.gram(m.tables(), "raw", centre=True)
    assert np.allclose(m.gram, g.S, rtol=1e-8, atol=1e-8 * np.abs(g.S).max())
    assert not np.allclose(m.gram[:-1, :-1], g_before)  # re-centred on the new mean


def test_fit_tool_adds_a_material_of_any_source_to_a_saved_manifold(tmp_path, monkeypatch):
    """``fit_manifold.py M.npz --add SET:NAME`` grows a saved manifold by a built-in set's material
    (not only a .binary file), keeps the others' points and records where it came from."""
    from mitsuba_manifold import Manifold
    from mitsuba_manifold.apps.cli import fit_manifold

    base, grown = tmp_path / "m.npz", tmp_path / "g.npz"
    monkeypatch.chdir(tmp_path)  # nothing may be written into the working directory
    assert fit_manifold.main(["nielsen@8x8x16", "--out", str(base), "--q", "2"]) in (0, None)
    assert fit_manifold.main([str(base), "--add", "rgl:paper_white", "--out", str(grown)]) in (
        0,
        None,
    )
    m0, m1 = Manifold.load(str(base)), Manifold.load(str(grown))
    assert m1.names == m0.names + ["paper_white"]
    np.testing.assert_array_equal(m1.latent[:-1], m0.latent)
    assert [a.origin for a in m1.added] == ["rgl:paper_white"]
    with pytest.raises(SystemExit) as exit_:
        fit_manifold.main([str(base), "--add", "rgl:no-such", "--out", str(tmp_path / "h.npz")])
    assert exit_.value.code == 2
    assert not (tmp_path / "h.npz").exists()
    assert sorted(f for f in os.listdir(tmp_path) if not f.startswith(".")) == ["g.npz", "m.npz"]


def test_fit_tool_refuses_fit_options_for_a_saved_manifold(tmp_path):
    """A saved manifold given as DATABASE takes --add only: fit options, or no --add, are
    refused in one line before anything is written."""
    from mitsuba_manifold.apps.cli import fit_manifold

    base = tmp_path / "m.npz"
    assert fit_manifold.main(["nielsen@8x8x16", "--out", str(base), "--q", "2"]) in (0, None)
    for argv in (
        [str(base), "--out", str(tmp_path / "a.npz")],
        [str(base), "--add", "rgl:paper_white", "--q", "3", "--out", str(tmp_path / "b.npz")],
    ):
        with pytest.raises(SystemExit) as exit_:
            fit_manifold.main(argv)
        assert exit_.value.code == 2
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == ["m.npz"]
