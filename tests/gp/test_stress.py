"""Tests of the layout's stress term (mitsuba_manifold.gp.stress) and its place in the GPLVM fit."""

import numpy as np
import pytest
from gp_synthetic import gram, smooth_data

from mitsuba_manifold.errors import InputError
from mitsuba_manifold.gp import gplvm
from mitsuba_manifold.gp.stress import Stress, neighbour_mask


def _targets(n, seed=0):
    P = np.random.default_rng(seed).standard_normal((n, 3))
    return np.linalg.norm(P[:, None] - P[None], axis=-1)


@pytest.mark.parametrize("k", [None, 3])
def test_gradient_matches_finite_differences(k):
    rng = np.random.default_rng(4)
    n, q = 12, 3
    term = Stress(0.5, k).term(_targets(n), n, 1000)
    X = rng.standard_normal((n, q))
    _, g = term.value_grad(X)
    h = 1e-6
    fd = np.zeros_like(X)
    for i in range(n):
        for j in range(q):
            Xp, Xm = X.copy(), X.copy()
            Xp[i, j] += h
            Xm[i, j] -= h
            fd[i, j] = (term.value(Xp) - term.value(Xm)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)
    assert np.abs(g).max() > 1e-3  # a gradient that is not trivially zero


def test_stress_is_zero_for_proportional_distances_and_scale_free():
    D = _targets(9, seed=2)
    P = np.random.default_rng(2).standard_normal((9, 3))  # the points D was made from
    term = Stress(1.0).term(D, 9, 10)
    assert term.value(P * 7.0) == pytest.approx(0.0, abs=1e-12)
    X = np.random.default_rng(5).standard_normal((9, 2))
    s = term.value(X)
    assert 0.05 < s <= 1.0
    assert term.value(3.0 * X) == pytest.approx(s, rel=1e-12)
    assert term.coefficient == pytest.approx(1.0 * 0.5 * 10 * 9)


def test_neighbour_mask_is_symmetric_and_holds_each_materials_nearest():
    D = _targets(10, seed=3)
    W = neighbour_mask(D, 2)
    assert (W == W.T).all() and (np.diag(W) == 0).all()
    near = np.argsort(D + np.diag(np.full(10, np.inf)), axis=1)[:, :2]
    for i in range(10):
        assert W[i, near[i]].all()
    assert 2 <= W.sum(1).min() and W.sum() < 90
    assert (neighbour_mask(D) == 1 - np.eye(10)).all()


def test_weight_zero_is_the_plain_fit_bit_for_bit():
    d = 1e5
    S = gram(smooth_data(12, seed=3), d)
    plain = gplvm.fit_latent(S, d, q=2, method="lbfgs")
    off = gplvm.GPLVM(2, method="lbfgs", stress=Stress(0.0, 3)).fit(S, d, distances=_targets(12))
    assert np.array_equal(plain.latent, off.latent)
    assert np.array_equal(plain.history, off.history)
    assert off.stress is None


def test_stress_term_pulls_the_layout_towards_the_targets():
    """A growing weight lowers the stress of the fitted points at the cost of L (Eq. 6)."""
    d = 1e4
    n = 16
    S = gram(smooth_data(n, seed=5), d)
    D = _targets(n, seed=6)  # unrelated to the data: the two aims pull apart
    term = Stress(1.0).term(D, n, d)
    plain = gplvm.fit_latent(S, d, q=2, method="lbfgs")
    fits = [
        gplvm.GPLVM(2, method="lbfgs", stress=Stress(w)).fit(S, d, distances=D) for w in (0.01, 1.0)
    ]
    sigmas = [term.value(plain.latent)] + [f.stress for f in fits]
    Ls = [plain.log_likelihood] + [f.log_likelihood for f in fits]
    assert sigmas[0] > sigmas[1] > sigmas[2]
    assert Ls[0] >= Ls[1] >= Ls[2]
    for f in fits:
        assert f.stress == pytest.approx(term.value(f.latent), rel=1e-12)
        assert np.all(np.diff(f.history) >= -1e-9 * abs(f.history[0]))


@pytest.mark.parametrize(
    "make, match",
    [
        (
            lambda: Stress(-1.0),
            r"`stress` \(the stress term.s weight\) must be a finite number >= 0, got -1.0",
        ),
        (lambda: Stress(float("nan")), "must be a finite number >= 0, got nan"),
        (lambda: Stress(True), r"`stress` \(the stress term.s weight\) must be a number, got True"),
        (lambda: Stress("0.5x"), "must be a number, got .0.5x."),
        (lambda: Stress(1.0, 0), "stress_neighbours"),
        (lambda: gplvm.GPLVM(2, stress=Stress(1.0)), "needs method 'newton' or 'lbfgs'"),
        (lambda: gplvm.GPLVM(2, method="lbfgs", stress=0.5), "must be a gplvm.Stress"),
        (
            lambda: gplvm.GPLVM(2, method="lbfgs", stress=Stress(1.0)).fit(np.eye(4), 10),
            "needs the target `distances`",
        ),
        (
            lambda: gplvm.GPLVM(2, method="lbfgs", stress=Stress(1.0)).fit(
                np.eye(4), 10, distances=np.ones((3, 3))
            ),
            "must be N x N",
        ),
        (
            lambda: gplvm.GPLVM(2, method="lbfgs", stress=Stress(1.0)).fit(
                np.eye(4), 10, distances=-np.ones((4, 4))
            ),
            r"finite and >= 0, got -1.0: .* or fit with stress=0.0",
        ),
        (
            lambda: gplvm.GPLVM(2, method="lbfgs", stress=Stress(1.0)).fit(
                np.eye(4), 10, distances=np.zeros((4, 4))
            ),
            r"all 0 .* fit with stress=0.0 \(--stress 0\)",
        ),
    ],
)
def test_bad_stress_settings_are_rejected_clearly(make, match):
    with pytest.raises(InputError, match=match):
        make()


def test_penalised_objective_gradient_matches_finite_differences():
    """The objective the optimiser climbs, ``L - lambda (d N / 2) sigma``, with its gradient."""
    from mitsuba_manifold.gp.likelihood import Likelihood
    from mitsuba_manifold.gp.stress import PenalisedLikelihood

    n, d = 10, 1e3
    S = gram(smooth_data(n, seed=8), d)
    unit = Likelihood(S, d).in_units()
    obj = PenalisedLikelihood(unit, Stress(0.3).term(_targets(n, seed=9), n, d))
    X = gplvm.pca_init(S, 2) + 0.1 * np.random.default_rng(1).standard_normal((n, 2))
    value, g = obj._value_grad(X)
    assert value == pytest.approx(unit._value(X) - obj.term.penalty(X), rel=1e-12)
    h = 1e-6
    fd = np.zeros_like(X)
    for i in range(n):
        for j in range(2):
            Xp, Xm = X.copy(), X.copy()
            Xp[i, j] += h
            Xm[i, j] -= h
            fd[i, j] = (obj._value(Xp) - obj._value(Xm)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_the_first_history_entry_is_the_penalised_objective_whatever_max_iter():
    """History holds L - lambda (d N / 2) sigma from its first entry on, also with no iteration."""
    S, d = gram(smooth_data(12, 40, seed=3)), 40
    D = _targets(12, seed=3)
    first = [
        gplvm.GPLVM(2, method="lbfgs", options=gplvm.LBFGSOptions(max_iter=k), stress=Stress(5.0))
        .fit(S, d, distances=D)
        .history[0]
        for k in (0, 1)
    ]
    assert first[0] == pytest.approx(first[1], rel=1e-12)
