"""A manifold's fit is a property of its tables: converged (and recorded so), the same layout
whatever the BLAS threads or the order the materials are named in, in the canonical pose."""

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from mitsuba_manifold.errors import ConvergenceWarning
from mitsuba_manifold.manifold.model import Manifold

NEW_KEYS = ("converged", "n_iterations", "grad_norm", "stop")


def _by_name(m):
    return {n: m.latent[i] for i, n in enumerate(m.names)}


def test_the_fit_records_its_convergence_and_the_summary_shows_it(small_db, tmp_path):
    m = Manifold.fit(small_db)
    info = m.info
    assert info["converged"] is True
    assert isinstance(info["n_iterations"], int) and info["n_iterations"] >= 1
    assert 0 <= info["grad_norm"] < 1e-3 and info["stop"]
    assert f"fit: converged ({info['n_iterations']} iterations" in m.summary()
    m.save(tmp_path / "m.npz")
    back = Manifold.load(tmp_path / "m.npz")
    assert {k: back.info[k] for k in NEW_KEYS} == {k: info[k] for k in NEW_KEYS}
    assert "fit: converged" in back.summary()


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_a_fit_stopped_by_its_cap_warns_and_says_so(small_db, preset):
    with pytest.warns(ConvergenceWarning, match="did not converge"):
        m = Manifold.fit(small_db, preset=preset, max_iter=1)
    assert m.info["converged"] is False and "max_iter" in m.info["stop"]
    assert "fit: NOT CONVERGED" in m.summary()


def test_a_manifold_saved_before_convergence_was_recorded_loads_as_unknown(small_db, tmp_path):
    m = Manifold.fit(small_db, q=2)
    m.info = {k: v for k, v in m.info.items() if k not in NEW_KEYS}
    m.save(tmp_path / "old.npz")
    old = Manifold.load(tmp_path / "old.npz")
    assert "converged" not in old.info
    assert "fit: convergence unknown" in old.summary()


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_the_layout_is_the_same_with_any_blas_threads_and_material_order(small_db, preset):
    with threadpool_limits(limits=1, user_api="blas"):
        one = Manifold.fit(small_db, preset=preset)
    with threadpool_limits(limits=2, user_api="blas"):
        two = Manifold.fit(small_db, preset=preset)
    shuffled = list(np.random.default_rng(3).permutation(one.names))
    other = Manifold.fit(small_db, preset=preset, names=shuffled)
    assert other.names == shuffled
    ref = _by_name(one)
    for m in (two, other):
        pts = _by_name(m)
        assert max(np.abs(pts[n] - ref[n]).max() for n in ref) < 1e-5


def test_the_layout_is_in_the_canonical_pose(small_db):
    X = Manifold.fit(small_db).latent
    assert np.abs(X.mean(axis=0)).max() < 1e-9
    cov = X.T @ X
    assert np.abs(cov - np.diag(np.diag(cov))).max() < 1e-9 * cov.max()
    assert np.all(np.diff(np.diag(cov)) <= 0)
    assert np.all((X**3).sum(axis=0) > 0)
