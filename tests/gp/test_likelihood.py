"""The likelihood objective (Eq. 6): against the dense formula, its invariances, its gradients with
respect to the points and the hyperparameters by finite differences, and the estimator built on it."""

import numpy as np
import pytest
from gp_synthetic import dense_log_likelihood, gram, smooth_data
from hypothesis import given, settings
from hypothesis import strategies as st

from mitsuba_manifold.errors import InputError
from mitsuba_manifold.gp import gplvm
from mitsuba_manifold.gp.kernel import Kernel
from mitsuba_manifold.gp.likelihood import Likelihood


@pytest.fixture(scope="module")
def problem():
    d = 1e6
    S = gram(smooth_data(24, seed=1), d)
    return S, d


def test_log_likelihood_matches_dense_formula(problem):
    S, d = problem
    X = np.random.default_rng(2).standard_normal((len(S), 3))
    L = gplvm.log_likelihood(X, S, d, length_scale=1.3, noise=1e-3)
    assert L == pytest.approx(dense_log_likelihood(X, S, d, 1.3, 1e-3), rel=1e-12)


@settings(max_examples=20, deadline=None)
@given(angle=st.floats(-3.2, 3.2), shift=st.tuples(st.floats(-5, 5), st.floats(-5, 5)))
def test_log_likelihood_invariant_under_rigid_motion(problem, angle, shift):
    S, d = problem
    X = gplvm.pca_init(S, 2)
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    L0 = gplvm.log_likelihood(X, S, d)
    assert gplvm.log_likelihood(X @ R + np.array(shift), S, d) == pytest.approx(L0, rel=1e-9)


@pytest.mark.parametrize("l", [1.0, 0.4])
def test_gradient_matches_finite_differences(problem, l):
    S, d = problem
    X = gplvm.pca_init(S, 3, length_scale=l)
    L, grad = gplvm.log_likelihood_grad(X, S, d, length_scale=l)
    assert L == pytest.approx(gplvm.log_likelihood(X, S, d, length_scale=l), rel=1e-13)
    assert grad.shape == X.shape
    h = 1e-5 * l
    for i, j in [(0, 0), (3, 1), (7, 2), (len(S) - 1, 0), (11, 1)]:
        Xp, Xm = X.copy(), X.copy()
        Xp[i, j] += h
        Xm[i, j] -= h
        num = (
            gplvm.log_likelihood(Xp, S, d, length_scale=l)
            - gplvm.log_likelihood(Xm, S, d, length_scale=l)
        ) / (2 * h)
        assert grad[i, j] == pytest.approx(num, rel=1e-5, abs=1e-6 * np.abs(grad).max())


def test_the_object_and_the_functions_agree(problem):
    S, d = problem
    X = gplvm.pca_init(S, 2, length_scale=0.8)
    lik = Likelihood(S, d, Kernel(0.8, 1e-3))
    assert lik(X) == gplvm.log_likelihood(X, S, d, length_scale=0.8, noise=1e-3)
    L, g = lik.gradient(X)
    L2, g2 = gplvm.log_likelihood_grad(X, S, d, length_scale=0.8, noise=1e-3)
    assert L == L2 and np.array_equal(g, g2)
    assert lik.in_units()(X / 0.8) == pytest.approx(
        L, rel=1e-12
    )  # scaling l and x together: same L


@pytest.mark.parametrize("l,mu", [(1.0, 1e-3), (0.6, 0.05)])
def test_gradient_theta_matches_finite_differences(problem, l, mu):
    S, d = problem
    X = gplvm.pca_init(S, 2, length_scale=1.0)
    L, g = Likelihood(S, d, Kernel(l, mu)).gradient_theta(X)
    assert L == pytest.approx(gplvm.log_likelihood(X, S, d, l, mu), rel=1e-12)
    for i, h in enumerate((1e-6 * l, 1e-6 * mu)):
        up, down = np.array([l, mu]), np.array([l, mu])
        up[i] += h
        down[i] -= h
        fd = (Likelihood(S, d, Kernel(*up))(X) - Likelihood(S, d, Kernel(*down))(X)) / (2 * h)
        assert g[i] == pytest.approx(fd, rel=1e-5)


def test_the_estimator_is_fit_latent(problem):
    S, d = problem
    res = gplvm.GPLVM(
        q=2, kernel=Kernel(1.0, 1e-4), method="lbfgs", options=gplvm.LBFGSOptions(max_iter=30)
    ).fit(S, d)
    ref = gplvm.fit_latent(S, d, q=2, method="lbfgs", options=gplvm.LBFGSOptions(max_iter=30))
    assert np.array_equal(res.latent, ref.latent) and res.kernel == Kernel(1.0, 1e-4)
    with pytest.raises(InputError, match="`options` of method 'lbfgs' must be a LBFGSOptions"):
        gplvm.GPLVM(method="lbfgs", options=gplvm.HookeJeevesOptions())
    with pytest.raises(InputError, match="`noise`"):
        gplvm.GPLVM(kernel=Kernel(1.0, 0.0))
    with pytest.raises(InputError, match="`max_iter`"):
        gplvm.HookeJeevesOptions(max_iter=True)
