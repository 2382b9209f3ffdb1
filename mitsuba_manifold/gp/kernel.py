"""The GPLVM's covariance function and the factorisation of its matrix (paper Eq. 5).

    c(x, x') = mu delta(x, x') + exp(-|x - x'|^2 / (2 l^2))

:func:`kernel_matrix` evaluates it; :func:`factorise` is the one Cholesky factorisation of
``K`` (with ``log|K|``) used by the likelihood, the rank-updated inverse, the optimisers
and :class:`~mitsuba_manifold.manifold.model.Manifold`. Latent points ``U`` in units of the
length scale (``u = x / l``) give ``K`` through :func:`cov`.
"""

import math
from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.spatial.distance

from ..errors import InputError, NotPositiveDefiniteError

#: Largest latent dimension accepted.
MAX_LATENT_DIM = 8


class Factor(NamedTuple):
    """Cholesky factorisation of K: ``cho`` as ``scipy.linalg.cho_factor`` returns it, and ``log|K|``."""

    cho: tuple
    logdet: float

    def solve(self, B):
        """``K^-1 B``."""
        return scipy.linalg.cho_solve(self.cho, B, check_finite=False)

    def inverse(self):
        """``K^-1``, symmetrised."""
        K_inv = self.solve(np.eye(self.cho[0].shape[0]))
        return 0.5 * (K_inv + K_inv.T)


def check_positive(name, value, allow_zero=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        need = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name} must be finite and {need}, got {value!r}")
    return v


def check_points(name, X, n=None, q=None):
    try:
        X = np.array(X, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name} must be a real numeric array: {e}") from None
    if X.ndim != 2:
        raise InputError(f"{name} must have shape (N, q), got {X.shape}")
    if n is not None and X.shape[0] != n:
        raise InputError(f"{name} has {X.shape[0]} points but S is {n} x {n}")
    if q is not None and X.shape[1] != q:
        raise InputError(f"{name} has dimension {X.shape[1]}, expected q = {q}")
    if not 1 <= X.shape[1] <= MAX_LATENT_DIM:
        raise InputError(f"{name} has latent dimension {X.shape[1]}; "
                         f"q must be from 1 to {MAX_LATENT_DIM}")
    if not np.all(np.isfinite(X)):
        row = int(np.argwhere(~np.isfinite(X))[0, 0])
        raise InputError(f"{name} has a non-finite coordinate in point {row}: {X[row]}")
    return X


def sq_dist(A, B):
    """Squared distances, summed from coordinate differences (no cancellation, no inf - inf)."""
    return scipy.spatial.distance.cdist(A, B, "sqeuclidean")


def cov(U, noise):
    """K for latent points ``U`` in units of the length scale."""
    K = np.exp(-0.5 * sq_dist(U, U))
    K[np.diag_indices_from(K)] = 1.0 + noise
    return K


def kernel_matrix(A, B=None, length_scale=1.0, noise=1e-4):
    """Covariance ``c(x, x') = mu delta(x, x') + exp(-|x - x'|^2 / (2 l^2))`` (Eq. 5).

    Parameters
    ----------
    A : (n, q) array_like
        Latent points.
    B : (m, q) array_like, optional
        Second set of points. If given, the cross-covariance ``exp(...)`` of shape
        ``(n, m)`` is returned, without the noise term (the vector ``k(x)`` of Eq. 1).
    length_scale, noise : float
        ``l > 0`` and ``mu >= 0``.

    Returns
    -------
    ndarray
        ``K`` (n x n, ``1 + mu`` on the diagonal) when ``B`` is None, else ``(n, m)``.
    """
    l = check_positive("length_scale", length_scale)
    mu = check_positive("noise", noise, allow_zero=True)
    A = check_points("A", A)
    if B is None:
        return cov(A / l, mu)
    B = check_points("B", B, q=A.shape[1])
    return np.exp(-0.5 * sq_dist(A / l, B / l))


def factorise(K):
    """Cholesky factor and ``log|K|`` (a :class:`Factor`), raising :class:`NotPositiveDefiniteError`."""
    try:
        cho = scipy.linalg.cho_factor(K, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        cho = None
    diag = None if cho is None else np.diag(cho[0])
    if cho is None or not np.all(np.isfinite(cho[0])) or not np.all(diag > 0):
        mu = K[0, 0] - 1.0
        raise NotPositiveDefiniteError(
            f"covariance matrix K ({K.shape[0]} x {K.shape[0]}) is not positive definite to "
            f"working precision (noise mu = {mu:.3g}); latent points probably coincide: use a "
            f"larger noise mu or separate the points")
    return Factor(cho, 2.0 * float(np.sum(np.log(diag))))
