"""The GPLVM log-likelihood and its gradient (paper Eq. 6).

    L = -d/2 log|K| - 1/2 tr(K^-1 S),      S = Z Z^T

Only the ``N x N`` Gram matrix ``S`` of the mean-subtracted observations and the number
of values ``d`` per material enter; the functions without a leading check work on latent
points in units of the length scale (``u = x / l``), as the optimisers do.
"""

import math
import numbers

import numpy as np

from ..errors import InputError
from .kernel import check_points, check_positive, cov, factorise


def check_gram(S, check_psd=True):
    """Return S as a symmetric float64 array, or raise ValueError saying what is wrong."""
    try:
        S = np.array(S, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"Gram matrix S must be a real numeric array: {e}") from None
    if S.ndim != 2 or S.shape[0] != S.shape[1]:
        raise InputError(f"Gram matrix S must be square (N x N), got shape {S.shape}")
    n = S.shape[0]
    if n < 2:
        raise InputError(f"need at least 2 materials to fit a manifold, S is {n} x {n}")
    if not np.all(np.isfinite(S)):
        bad = np.argwhere(~np.isfinite(S))[0]
        raise InputError(f"Gram matrix S has a non-finite entry ({S[tuple(bad)]}) at {tuple(bad)}")
    scale = np.abs(S).max()
    asym = np.abs(S - S.T).max()
    if asym > 1e-8 * scale:
        raise InputError(f"Gram matrix S is not symmetric (max |S - S^T| = {asym:.3g}, "
                         f"max |S| = {scale:.3g})")
    S = 0.5 * (S + S.T)
    if check_psd and scale > 0:
        ev = np.linalg.eigvalsh(S)
        if ev[0] < -1e-8 * max(ev[-1], 0.0) or ev[-1] <= 0:
            raise InputError(
                f"Gram matrix S is not positive semi-definite (eigenvalues from {ev[0]:.3g} to "
                f"{ev[-1]:.3g}); it must be Z Z^T of the mean-subtracted observations")
    return S


def check_d(d):
    if isinstance(d, (bool, np.bool_)) or not isinstance(d, numbers.Real):
        raise InputError(f"d (number of values per material) must be an integer >= 1, got {d!r}")
    d = float(d)
    if not math.isfinite(d) or d < 1 or d != round(d):
        raise InputError(f"d (number of values per material) must be an integer >= 1, got {d!r}")
    return d




def objective(logdet, trace, d):
    return -0.5 * d * logdet - 0.5 * trace


def value_u(U, S, d, noise):
    f = factorise(cov(U, noise))
    return objective(f.logdet, float(np.trace(f.solve(S))), d)


def value_grad_u(U, S, d, noise):
    """L and dL/dU for latent points in units of the length scale."""
    K = cov(U, noise)
    f = factorise(K)
    K_inv = f.inverse()
    KS = K_inv @ S
    L = objective(f.logdet, float(np.trace(KS)), d)
    # dL = 1/2 tr(G dK) with G = K_inv S K_inv - d K_inv; dK_ij/du_i = -E_ij (u_i - u_j)
    G = KS @ K_inv - d * K_inv
    W = G * K
    W[np.diag_indices_from(W)] = 0.0
    grad = W @ U - W.sum(axis=1)[:, None] * U
    return L, grad


def log_likelihood(latent, S, d, length_scale=1.0, noise=1e-4):
    """Log-likelihood ``L = -d/2 log|K| - 1/2 tr(K_inv S)`` of latent points (Eq. 6).

    Parameters
    ----------
    latent : (N, q) array_like
        Latent points, one per material.
    S : (N, N) array_like
        Gram matrix ``Z Z^T`` of the mean-subtracted observations.
    d : int
        Number of values per material (columns of Z).
    length_scale, noise : float
        ``l > 0`` and ``mu > 0`` of the covariance function.

    Raises
    ------
    NotPositiveDefiniteError
        If K cannot be factorised (a ``numpy.linalg.LinAlgError``).
    ValueError
        On invalid input.
    """
    S = check_gram(S)
    d = check_d(d)
    l = check_positive("length_scale", length_scale)
    mu = check_positive("noise", noise)
    X = check_points("latent", latent, n=S.shape[0])
    return value_u(X / l, S, d, mu)


def log_likelihood_grad(latent, S, d, length_scale=1.0, noise=1e-4):
    """Log-likelihood and its analytic gradient with respect to the latent points.

    With ``G = K_inv S K_inv - d K_inv``, ``dL/dx_i = -sum_j G_ij K_ij (x_i - x_j) / l^2``.
    Same parameters as :func:`log_likelihood`.

    Returns
    -------
    L : float
    grad : (N, q) ndarray
    """
    S = check_gram(S)
    d = check_d(d)
    l = check_positive("length_scale", length_scale)
    mu = check_positive("noise", noise)
    X = check_points("latent", latent, n=S.shape[0])
    L, grad_u = value_grad_u(X / l, S, d, mu)
    return L, grad_u / l
