"""The GPLVM's covariance function as an object, and the one factorisation of its matrix (paper Eq. 5).

    c(x, x') = mu delta(x, x') + exp(-|x - x'|^2 / (2 l^2))

:class:`Kernel` holds the hyperparameters (length scale ``l``, noise ``mu``) and gives the
covariance matrix ``K(X)``, the cross-covariance ``K(X, X*)`` (the vector ``k_*`` of Eq. 3),
the gradients ``dk/dx`` and ``dK/dtheta`` and :meth:`Kernel.factorise`. In GPy terms it is
``RBF + White``, in scikit-learn's ``RBF() + WhiteKernel()``: the noise enters ``K(X)`` but
not the cross-covariance between distinct point sets.

:class:`Factor` (from :func:`factorise`) is the one Cholesky factorisation of ``K`` (solve,
inverse, ``log|K|``) used by the likelihood, the rank-updated inverse, the optimisers, the
GP posterior (:mod:`.posterior`) and through it the interpolant and
:class:`~mitsuba_manifold.manifold.model.Manifold`. Latent points ``U`` in units of the
length scale (``u = x / l``) are what :meth:`Kernel.in_units` works on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
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

    def solve(self, B) -> np.ndarray:
        """``K^-1 B``."""
        return scipy.linalg.cho_solve(self.cho, B, check_finite=False)

    def inverse(self) -> np.ndarray:
        """``K^-1``, symmetrised."""
        K_inv = self.solve(np.eye(self.cho[0].shape[0]))
        return 0.5 * (K_inv + K_inv.T)


def check_positive(name, value, allow_zero=False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"`{name}` must be a real number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        need = ">= 0" if allow_zero else "> 0"
        raise InputError(f"`{name}` must be finite and {need}, got {value!r}")
    return v


def check_points(name, X, n=None, q=None) -> np.ndarray:
    try:
        X = np.array(X, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"`{name}` must be a real numeric array: {e}") from None
    if X.ndim != 2:
        raise InputError(f"`{name}` must have shape (N, q), got {X.shape}")
    if n is not None and X.shape[0] != n:
        raise InputError(f"`{name}` has {X.shape[0]} points but S is {n} x {n}")
    if q is not None and X.shape[1] != q:
        raise InputError(f"`{name}` has dimension {X.shape[1]}, expected q = {q}")
    if not 1 <= X.shape[1] <= MAX_LATENT_DIM:
        raise InputError(
            f"`{name}` has latent dimension {X.shape[1]}; q must be from 1 to {MAX_LATENT_DIM}"
        )
    if not np.all(np.isfinite(X)):
        row = int(np.argwhere(~np.isfinite(X))[0, 0])
        raise InputError(f"`{name}` has a non-finite coordinate in point {row}: {X[row]}")
    return X


def sq_dist(A, B) -> np.ndarray:
    """Squared distances, summed from coordinate differences (no cancellation, no inf - inf)."""
    return scipy.spatial.distance.cdist(A, B, "sqeuclidean")


def factorise(K) -> Factor:
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
            f"larger `noise` mu or separate the points"
        )
    return Factor(cho, 2.0 * float(np.sum(np.log(diag))))


@dataclass(frozen=True)
class Kernel:
    """``c(x, x') = mu delta(x, x') + exp(-|x - x'|^2 / (2 l^2))`` (paper Eq. 5).

    Parameters
    ----------
    length_scale : float
        ``l > 0``, the characteristic length scale.
    noise : float
        ``mu >= 0``, the noise-filtering term on the diagonal of ``K``.

    The methods without a leading underscore check their points (``(n, q)`` arrays of finite
    numbers); ``_K`` and ``_cross`` are their unchecked cores for the optimisers' inner loops.
    """

    length_scale: float = 1.0
    noise: float = 1e-4

    #: Names of the hyperparameters, in the order of :attr:`theta` and :meth:`dK_dtheta`.
    hyperparameters = ("length_scale", "noise")

    def __post_init__(self) -> None:
        object.__setattr__(self, "length_scale", check_positive("length_scale", self.length_scale))
        object.__setattr__(self, "noise", check_positive("noise", self.noise, allow_zero=True))

    @property
    def theta(self) -> np.ndarray:
        """``[l, mu]`` (plain values; scikit-learn's ``theta`` holds their logarithms)."""
        return np.array([self.length_scale, self.noise])

    def in_units(self) -> Kernel:
        """The same kernel on points in units of the length scale (``u = x / l``): ``l = 1``."""
        return Kernel(1.0, self.noise)

    # -- covariances
    def K(self, X, X2=None) -> np.ndarray:
        """``K(X)`` (n x n, ``1 + mu`` on the diagonal), or the cross-covariance ``(n, m)``
        with ``X2`` (the smooth part only, the vector ``k_*`` of Eq. 3: no noise term).
        """
        X = check_points("A", X)
        if X2 is None:
            return self._K(X)
        return self._cross(X, check_points("B", X2, q=X.shape[1]))

    def Kdiag(self, X) -> np.ndarray:
        """``c(x, x) = 1 + mu`` for each point (the prior variance)."""
        return np.full(len(check_points("X", X)), 1.0 + self.noise)

    def cross(self, x, X, exact=False) -> np.ndarray:
        """``k(x)`` (M, N): covariances of points ``x`` with ``X``; with ``exact`` the noise term
        ``mu delta(x, x_i)`` is added where a row of ``x`` equals a point of ``X`` exactly.
        """
        k = self._cross(x, X)
        if exact:
            k[coincident(x, X)] += self.noise
        return k

    def _K(self, X) -> np.ndarray:
        U = X / self.length_scale
        K = np.exp(-0.5 * sq_dist(U, U))
        K[np.diag_indices_from(K)] = 1.0 + self.noise
        return K

    def _cross(self, A, B) -> np.ndarray:
        return np.exp(-0.5 * sq_dist(A / self.length_scale, B / self.length_scale))

    # -- gradients
    def dK_dx(self, x, X, k=None) -> np.ndarray:
        """``d k(x_m, X_n) / d x_m`` (M, N, q) ``= -k (x_m - X_n) / l^2``; ``k`` is
        :meth:`cross` ``(x, X)`` when already computed.
        """
        k = self._cross(x, X) if k is None else k
        return -k[:, :, None] * (x[:, None, :] - X[None]) / self.length_scale**2

    def dK_dtheta(self, X) -> np.ndarray:
        """``dK/dl`` and ``dK/dmu`` of ``K(X)``, stacked ``(2, n, n)``.

        ``dK_ij/dl = exp(-r_ij^2 / 2 l^2) r_ij^2 / l^3`` (zero on the diagonal) and
        ``dK/dmu = I``.
        """
        X = check_points("X", X)
        r2 = sq_dist(X, X)
        dl = np.exp(-0.5 * r2 / self.length_scale**2) * r2 / self.length_scale**3
        return np.stack([dl, np.eye(len(X))])

    # -- factorisation
    def factorise(self, X) -> Factor:
        """The :class:`Factor` of ``K(X)`` (:class:`NotPositiveDefiniteError` if it has none)."""
        return factorise(self.K(X))


def coincident(x, X) -> tuple[np.ndarray, ...]:
    """Index pairs (row of ``x``, row of ``X``) of points that are exactly equal: where the
    kernel's ``delta(x, x')`` is 1.
    """
    return np.nonzero((x[:, None, :] == X[None, :, :]).all(-1))


def kernel_matrix(A, B=None, length_scale=1.0, noise=1e-4) -> np.ndarray:
    """Covariance ``c(x, x') = mu delta(x, x') + exp(-|x - x'|^2 / (2 l^2))`` (Eq. 5).

    ``Kernel(length_scale, noise).K(A, B)``: ``K`` (n x n, ``1 + mu`` on the diagonal) when
    ``B`` is None, else the cross-covariance ``(n, m)`` without the noise term (the vector
    ``k(x)`` of Eq. 3).
    """
    return Kernel(length_scale, noise).K(A, B)
