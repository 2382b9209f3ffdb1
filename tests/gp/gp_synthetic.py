"""Synthetic data of the GP tests: Gram matrices of rows on a smooth hidden manifold, and Eq. 6 in plain NumPy."""

import numpy as np


def gram(Z, d=None):
    """Gram matrix of the mean-subtracted rows of Z, scaled as if Z had d columns."""
    Z = Z - Z.mean(axis=0)
    S = Z @ Z.T
    S = 0.5 * (S + S.T)
    return S if d is None else S * (d / Z.shape[1])


def smooth_data(n, dd=300, hidden=2, seed=0):
    """Rows that vary smoothly with hidden low-dimensional coordinates (a true manifold)."""
    rng = np.random.default_rng(seed)
    t = rng.standard_normal((n, hidden))
    features = np.cos(t @ rng.standard_normal((hidden, 24)) + rng.uniform(0, 6, 24))
    return features @ rng.standard_normal((24, dd)) + 0.01 * rng.standard_normal((n, dd))


def dense_log_likelihood(X, S, d, l, mu):
    """Eq. 6 written with plain NumPy (slogdet and solve), the reference."""
    diff = X[:, None, :] - X[None, :, :]
    K = np.exp(-np.sum(diff**2, axis=-1) / (2 * l * l)) + mu * np.eye(len(X))
    sign, logdet = np.linalg.slogdet(K)
    assert sign > 0
    return -0.5 * d * logdet - 0.5 * np.trace(np.linalg.solve(K, S))
