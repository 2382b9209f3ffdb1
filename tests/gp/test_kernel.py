"""The kernel object (Eq. 5), its gradients by finite differences, its factorisation and the GP posterior (Eq. 1-4)."""

import numpy as np
import pytest

from mitsuba_manifold.errors import InputError, NotPositiveDefiniteError
from mitsuba_manifold.gp import gplvm
from mitsuba_manifold.gp.kernel import Kernel
from mitsuba_manifold.gp.posterior import Posterior


def _points(n=7, q=3, seed=0, spread=1.0):
    return np.random.default_rng(seed).standard_normal((n, q)) * spread


def test_kernel_matrix_is_eq5():
    rng = np.random.default_rng(0)
    A, B = rng.standard_normal((5, 3)), rng.standard_normal((4, 3))
    K = gplvm.kernel_matrix(A, length_scale=0.7, noise=1e-3)
    ref = np.exp(-((A[:, None] - A[None]) ** 2).sum(-1) / (2 * 0.49)) + 1e-3 * np.eye(5)
    np.testing.assert_allclose(K, ref, rtol=1e-14)
    cross = gplvm.kernel_matrix(A, B, length_scale=0.7, noise=1e-3)
    assert cross.shape == (5, 4)
    np.testing.assert_allclose(
        cross, np.exp(-((A[:, None] - B[None]) ** 2).sum(-1) / (2 * 0.49)), rtol=1e-14
    )
    # no noise in the cross-covariance, even at coincident points
    assert gplvm.kernel_matrix(A, A[:2], noise=0.5)[0, 0] == 1.0
    # the function is the object's K
    k = Kernel(0.7, 1e-3)
    assert np.array_equal(k.K(A), K) and np.array_equal(k.K(A, B), cross)
    assert np.array_equal(k.Kdiag(A), np.diag(K))


def test_exact_cross_covariance_adds_the_noise_only_at_equal_points():
    X = _points()
    k = Kernel(0.8, 0.01)
    x = np.vstack([X[2], X[2] + 1e-12, X[5]])
    exact, smooth = k.cross(x, X, exact=True), k.cross(x, X)
    diff = exact - smooth
    assert diff[0, 2] == pytest.approx(0.01) and diff[2, 5] == pytest.approx(0.01)
    assert np.count_nonzero(diff) == 2
    np.testing.assert_array_equal(exact[0], k.K(X)[2])  # column i of K: the training point's k


@pytest.mark.parametrize("l", [0.5, 1.0, 3.0])
def test_dK_dx_matches_finite_differences(l):
    X = _points(6, 2, seed=1)
    x = _points(4, 2, seed=2)
    k = Kernel(l, 1e-4)
    J = k.dK_dx(x, X)
    assert J.shape == (4, 6, 2)
    h = 1e-6 * l
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (k.cross(x + e, X) - k.cross(x - e, X)) / (2 * h)
        np.testing.assert_allclose(J[..., j], fd, rtol=1e-6, atol=1e-10)
    np.testing.assert_array_equal(k.dK_dx(x, X, k.cross(x, X)), J)


@pytest.mark.parametrize("l,mu", [(0.7, 1e-3), (2.0, 0.1)])
def test_dK_dtheta_matches_finite_differences(l, mu):
    X = _points(6, 3, seed=3)
    D = Kernel(l, mu).dK_dtheta(X)
    assert D.shape == (2, 6, 6) and Kernel.hyperparameters == ("length_scale", "noise")
    for i, h in enumerate((1e-6 * l, 1e-6 * mu)):
        up, down = np.array([l, mu]), np.array([l, mu])
        up[i] += h
        down[i] -= h
        fd = (Kernel(*up).K(X) - Kernel(*down).K(X)) / (2 * h)
        np.testing.assert_allclose(D[i], fd, rtol=1e-6, atol=1e-9)
    assert np.array_equal(Kernel(l, mu).theta, [l, mu])


def test_factor_solves_inverts_and_gives_the_log_determinant():
    X = _points(8, 2, seed=4)
    k = Kernel(1.3, 1e-3)
    f = k.factorise(X)
    K = k.K(X)
    B = np.random.default_rng(5).standard_normal((8, 3))
    np.testing.assert_allclose(K @ f.solve(B), B, atol=1e-9)
    np.testing.assert_allclose(f.inverse() @ K, np.eye(8), atol=1e-8)
    assert np.array_equal(f.inverse(), f.inverse().T)
    assert f.logdet == pytest.approx(np.linalg.slogdet(K)[1], rel=1e-12)


def test_kernel_refuses_bad_hyperparameters_and_factorises_only_positive_definite_K():
    for kwargs, match in [
        ({"length_scale": 0.0}, "`length_scale`"),
        ({"length_scale": np.inf}, "`length_scale`"),
        ({"noise": -1e-3}, "`noise`"),
        ({"noise": "much"}, "`noise`"),
    ]:
        with pytest.raises(InputError, match=match):
            Kernel(**kwargs)
    X = _points(4, 2)
    X[1] = X[0]
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        Kernel(1.0, 0.0).factorise(X)
    assert Kernel(1.0, 1e-4).factorise(X).logdet < 0  # the noise separates them


def test_posterior_is_eq1_to_4_with_one_factorisation():
    X = _points(9, 2, seed=6, spread=1.5)
    kernel = Kernel(0.9, 1e-4)
    gp = Posterior(X, kernel)
    K = kernel.K(X)
    x = _points(5, 2, seed=7)
    k = kernel.K(x, X)
    np.testing.assert_allclose(gp.weights(x), np.linalg.solve(K, k.T).T, rtol=1e-8, atol=1e-10)
    var = 1 + kernel.noise - np.einsum("mn,nm->m", k, np.linalg.solve(K, k.T))
    np.testing.assert_allclose(gp.variance(x), var, rtol=1e-8, atol=1e-12)
    assert gp.variance(X[3:4])[0] == pytest.approx(
        0.0, abs=1e-9
    )  # the noise term at a training point
    assert gp.condition_number() == pytest.approx(np.linalg.cond(K), rel=1e-6)
    h = 1e-6
    J, G = gp.weights_jacobian(x), gp.variance_gradient(x)
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        np.testing.assert_allclose(
            J[..., j], (gp.weights(x + e) - gp.weights(x - e)) / (2 * h), rtol=1e-5, atol=1e-7
        )
        np.testing.assert_allclose(
            G[:, j], (gp.variance(x + e) - gp.variance(x - e)) / (2 * h), rtol=1e-5, atol=1e-8
        )
